// Phi's output gradient (sunaware/model.rs `backward_timed`): for r < count,
// d_out[r * 3 + k] = rows[g * (13 + nc) + 13 + k], g = list[r], the rasterizer's gradient
// of channel k; rows r >= count are zeros.
//
// With `shaded` (Shading::LambertLearned, sunaware/shading.rs `shade_backward`, in its
// order of operations): with (f, sign) = shade[2r..2r + 2] from the scatter and c = Phi's
// unshaded output of row r, d_out = f d and, where sign != 0 (lit) and
// dL/df = d . c != 0, the normal's gradient
// dL/df (1 - k_a) sign / |v| (s - n (n . s)), n = v / |v|, is ADDED to the Normal row g
// of `grads` when all three values are finite (the caller cleared the group).

@group(0) @binding(3) var<storage, read> rows: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_out: array<f32>;
@group(0) @binding(5) var<storage, read> params: array<f32>;
@group(0) @binding(6) var<storage, read> shade: array<f32>;
@group(0) @binding(7) var<storage, read> phi_out: array<f32>;
@group(0) @binding(8) var<storage, read_write> grads: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    if r >= u.n {
        return;
    }
    let g = listed_gaussian(r);
    var d = vec3<f32>(0.0);
    if g < u.n {
        let at = g * (13u + u.nc) + 13u;
        d = vec3<f32>(rows[at], rows[at + 1u], rows[at + 2u]);
    }
    if u.shaded == 0u || g >= u.n {
        for (var k = 0u; k < 3u; k++) {
            d_out[r * 3u + k] = d[k];
        }
        return;
    }
    let f = shade[2u * r];
    let sign = shade[2u * r + 1u];
    let c = vec3<f32>(phi_out[r * 3u], phi_out[r * 3u + 1u], phi_out[r * 3u + 2u]);
    let d_f = d.x * c.x + d.y * c.y + d.z * c.z;
    for (var k = 0u; k < 3u; k++) {
        d_out[r * 3u + k] = d[k] * f;
    }
    if sign == 0.0 || d_f == 0.0 {
        return;
    }
    let no = u.normal_off + 3u * g;
    let v = vec3<f32>(params[no], params[no + 1u], params[no + 2u]);
    let v_norm = sqrt(v.x * v.x + v.y * v.y + v.z * v.z);
    let n_hat = vec3<f32>(v.x / v_norm, v.y / v_norm, v.z / v_norm);
    let s = u.sun_unit;
    let n_dot_s = n_hat.x * s.x + n_hat.y * s.y + n_hat.z * s.z;
    let scale = d_f * (1.0 - u.ambient) * sign / v_norm;
    var grad = vec3<f32>(
        scale * (s.x - n_hat.x * n_dot_s),
        scale * (s.y - n_hat.y * n_dot_s),
        scale * (s.z - n_hat.z * n_dot_s),
    );
    if finite(grad.x) && finite(grad.y) && finite(grad.z) {
        for (var k = 0u; k < 3u; k++) {
            grads[no + k] = grads[no + k] + grad[k];
        }
    }
}
