// Visible Gaussians of the Sun-aware resident step: flag[i] = 1 where the projection
// kept Gaussian i (splat radius >= 0; culled splats carry -1, the CPU's `None`), and
// flag[n] = 0, so the exclusive prefix sum numbers the survivors in index order and its
// last value is their count.

@group(0) @binding(0) var<uniform> c: Count;
@group(0) @binding(1) var<storage, read> splats: array<f32>;
@group(0) @binding(2) var<storage, read_write> flag: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i == 0u {
        flag[c.n] = 0u;
    }
    if i >= c.n {
        return;
    }
    flag[i] = select(0u, 1u, splats[12u * i + 7u] >= 0.0);
}
