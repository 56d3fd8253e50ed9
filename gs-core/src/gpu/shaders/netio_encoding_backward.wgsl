// Included by the input-gradient kernels (after netio_common.wgsl), which bind `d_input`.

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
