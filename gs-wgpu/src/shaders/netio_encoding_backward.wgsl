// Prepended to the input-gradient kernels (netio_phi_input_grad, netio_psi_input_grad),
// after netio_common.wgsl: their shared bindings (the packed parameters, the input rows'
// gradient, the packed gradient) and the encoding's backward.

@group(0) @binding(3) var<storage, read> params: array<f32>;
@group(0) @binding(4) var<storage, read> d_input: array<f32>;
@group(0) @binding(5) var<storage, read_write> grads: array<f32>;

// d p_c of gamma_L at p_c (sines and cosines recomputed, the same bits as encoding.rs
// `backward_from_code` on `encode_unchecked`'s output): sum over k of
// 2^k pi (cos * d_sin - sin * d_cos), in band order; `d_code` indexes d_input at the
// sine column of (component c, band 0).
fn encoding_backward(u: NetIo, p: f32, d_code: u32) -> f32 {
    var acc = 0.0;
    for (var k = 0u; k < u.freqs; k++) {
        let sc = sin_cos_pi(p * f32(1u << k));
        acc += omega(k) * (sc.y * d_input[d_code + 2u * k] - sc.x * d_input[d_code + 2u * k + 1u]);
    }
    return acc;
}
