// Pointwise parts of the device MLP (mlp/), one thread per value of a row-major
// `count / n` x `n` matrix `x`, in place. op 0, 1, 2: add the bias aux[aux_off + j], then
// ReLU, LeakyReLU (negative slope u.slope) or the sigmoid (forward). op 3: dY -> dZ =
// y (1 - y) dY through the output sigmoid, y = aux[aux_off + i]. op 4, 5: multiply by the
// ReLU / LeakyReLU slope, read from the post-activation value aux[aux_off + i] (its sign is
// the pre-activation's), as nn/mlp.rs. Rows r >= live[0] (dead rows of the batch, the
// count read on the device) are written 0 and read nothing.

struct Pointwise {
    count: u32,
    n: u32,
    op: u32,
    slope: f32,
    aux_off: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> u: Pointwise;
@group(0) @binding(1) var<storage, read_write> x: array<f32>;
@group(0) @binding(2) var<storage, read> aux: array<f32>;
@group(0) @binding(3) var<storage, read> live: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= u.count {
        return;
    }
    if i / u.n >= live[0] {
        x[i] = 0.0;
        return;
    }
    let v = x[i];
    switch u.op {
        case 0u: {
            x[i] = max(v + aux[u.aux_off + i % u.n], 0.0);
        }
        case 1u: {
            let z = v + aux[u.aux_off + i % u.n];
            x[i] = select(u.slope * z, z, z > 0.0);
        }
        case 2u: {
            x[i] = 1.0 / (1.0 + exp(-(v + aux[u.aux_off + i % u.n])));
        }
        case 3u: {
            let y = aux[u.aux_off + i];
            x[i] = y * (1.0 - y) * v;
        }
        case 4u: {
            x[i] = select(0.0, v, aux[u.aux_off + i] > 0.0);
        }
        default: {
            x[i] = select(u.slope * v, v, aux[u.aux_off + i] > 0.0);
        }
    }
}
