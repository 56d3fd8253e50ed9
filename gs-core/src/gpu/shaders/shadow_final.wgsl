// Shadow pass, stage 4: V = sum(w T) / sum(w), clamped to [0, 1]; 1 where no pixel saw
// the Gaussian (nothing is known to block the Sun).

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> sums: array<f32>;
@group(0) @binding(2) var<storage, read_write> vis: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = gid.x + gid.y * nwg.x * 256u;
    if g >= fr.n {
        return;
    }
    let w = sums[2u * g];
    var v = 1.0;
    if w > 0.0 {
        v = clamp(sums[2u * g + 1u] / w, 0.0, 1.0);
    }
    vis[g] = v;
}
