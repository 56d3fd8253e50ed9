// Adam on device-resident parameters: one thread per value of the packed, group-major
// parameter buffer (group g holds values [off[g], off[g + 1])). The same update as
// optim.rs (torch's formulation, ported operation for operation):
//   m = b1 m + (1 - b1) g;  v = b2 v + (1 - b2) g g;
//   x -= step_size * m / (sqrt(v) * inv_sqrt_bias2 + eps),  step_size = lr / bias1,
// with step_size and inv_sqrt_bias2 computed on the host in f64 as optim.rs does. Groups
// with learning rate 0 are left untouched, moments included. When `skip[0]` is non-zero
// (a non-finite gradient somewhere in the step) nothing is changed.

struct AdamUniform {
    // Group start offsets 0..8 and the total length (offsets[9]) in .x.y.z.w order.
    off0: vec4<u32>,
    off1: vec4<u32>,
    off2: vec4<u32>,
    // Per-group step size of groups 0..7 (0 for a frozen group).
    step0: vec4<f32>,
    step1: vec4<f32>,
    // Bit g set: group g takes a step.
    active_groups: u32,
    b1: f32,
    b2: f32,
    eps: f32,
    inv_sqrt_bias2: f32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
    // Step size of group 8 (the learned shading normal) in .x.
    step2: vec4<f32>,
}

@group(0) @binding(0) var<uniform> u: AdamUniform;
@group(0) @binding(1) var<storage, read_write> x: array<f32>;
@group(0) @binding(2) var<storage, read> grad: array<f32>;
@group(0) @binding(3) var<storage, read_write> m: array<f32>;
@group(0) @binding(4) var<storage, read_write> v: array<f32>;
@group(0) @binding(5) var<storage, read> skip: array<u32>;

fn offset(g: u32) -> u32 {
    if g < 4u {
        return u.off0[g];
    }
    if g < 8u {
        return u.off1[g - 4u];
    }
    return u.off2[g - 8u];
}

fn step_size(g: u32) -> f32 {
    if g < 4u {
        return u.step0[g];
    }
    if g < 8u {
        return u.step1[g - 4u];
    }
    return u.step2.x;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= u.off2[1] || skip[0] != 0u {
        return;
    }
    var g = 0u;
    for (var k = 1u; k < 9u; k++) {
        if i >= offset(k) {
            g = k;
        }
    }
    if (u.active_groups & (1u << g)) == 0u {
        return;
    }
    let gi = grad[i];
    let mi = u.b1 * m[i] + (1.0 - u.b1) * gi;
    let vi = u.b2 * v[i] + (1.0 - u.b2) * gi * gi;
    m[i] = mi;
    v[i] = vi;
    let denom = sqrt(vi) * u.inv_sqrt_bias2 + u.eps;
    x[i] = x[i] - step_size(g) * mi / denom;
}
