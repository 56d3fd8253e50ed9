// Shadow pass, stage 4: V = sum(w T) / sum(w), clamped to [0, 1]; 1 where no pixel saw
// the Gaussian (nothing is known to block the Sun). The sums are shadow_vis.wgsl's
// fixed-point pairs (fraction in 2^-32 units, integer part).

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> sums: array<u32>;
@group(0) @binding(2) var<storage, read_write> vis: array<f32>;

// The fixed-point pair at words k (fraction) and k + 1 (integer part) as f32.
fn fixed_sum(k: u32) -> f32 {
    return f32(sums[k + 1u]) + f32(sums[k]) * 2.3283064e-10;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = gid.x + gid.y * nwg.x * 256u;
    if g >= fr.n {
        return;
    }
    let w = fixed_sum(4u * g);
    var v = 1.0;
    if w > 0.0 {
        v = clamp(fixed_sum(4u * g + 2u) / w, 0.0, 1.0);
    }
    vis[g] = v;
}
