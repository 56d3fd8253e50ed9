// Bias gradient of the device MLP (gpu/mlp.rs): dst[j] = sum over rows r of
// src[r * n + j], one thread per column summing in row order (deterministic).

struct ColSum {
    rows: u32,
    n: u32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(0) var<uniform> u: ColSum;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if j >= u.n {
        return;
    }
    var sum = 0.0;
    for (var r = 0u; r < u.rows; r++) {
        sum += src[r * u.n + j];
    }
    dst[j] = sum;
}
