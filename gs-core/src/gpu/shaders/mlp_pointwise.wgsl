// Pointwise parts of the device MLP (gpu/mlp.rs), one thread per value of a row-major
// `count / n` x `n` matrix `x`, in place. op 0, 1, 2: add the bias aux[j], then ReLU,
// LeakyReLU (negative slope u.slope) or the sigmoid (forward). op 3: dY -> dZ = y (1 - y) dY
// through the output sigmoid, y = aux. op 4, 5: multiply by the ReLU / LeakyReLU slope,
// read from the post-activation value aux (its sign is the pre-activation's), as nn/mlp.rs.

struct Pointwise {
    count: u32,
    n: u32,
    op: u32,
    slope: f32,
}

@group(0) @binding(0) var<uniform> u: Pointwise;
@group(0) @binding(1) var<storage, read_write> x: array<f32>;
@group(0) @binding(2) var<storage, read> aux: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= u.count {
        return;
    }
    let v = x[i];
    switch u.op {
        case 0u: {
            x[i] = max(v + aux[i % u.n], 0.0);
        }
        case 1u: {
            let z = v + aux[i % u.n];
            x[i] = select(u.slope * z, z, z > 0.0);
        }
        case 2u: {
            x[i] = 1.0 / (1.0 + exp(-(v + aux[i % u.n])));
        }
        case 3u: {
            let y = aux[i];
            x[i] = y * (1.0 - y) * v;
        }
        case 4u: {
            x[i] = select(0.0, v, aux[i] > 0.0);
        }
        default: {
            x[i] = select(u.slope * v, v, aux[i] > 0.0);
        }
    }
}
