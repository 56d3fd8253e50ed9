// Bias gradient of the device MLP (mlp/): dst[dst_off + j] = sum over the live rows
// r < min(rows, live[0]) (the count read on the device) of src[r * n + j], one thread per
// column summing in row order (deterministic).

struct ColSum {
    rows: u32,
    n: u32,
    dst_off: u32,
    pad0: u32,
}

@group(0) @binding(0) var<uniform> u: ColSum;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;
@group(0) @binding(3) var<storage, read> live: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if j >= u.n {
        return;
    }
    let rows = min(u.rows, live[0]);
    var sum = 0.0;
    for (var r = 0u; r < rows; r++) {
        sum += src[r * u.n + j];
    }
    dst[u.dst_off + j] = sum;
}
