// Prepended to Phi's kernels that read the learned normal (netio_phi_scatter,
// netio_phi_input, netio_phi_input_grad), after netio_common.wgsl: the learned normal
// turned toward the camera (sunaware/shading.rs `learned_facing_normal`, `turned_toward`)
// and the local frame of Phi's local inputs (`local_frame`, `local_inputs`,
// `local_inputs_backward`), ported operation for operation in the CPU's order. The
// functions take values, not buffers: each kernel reads its own `params` binding. They
// read the uniform's `cam`, `sun_unit` (.w: MIN_HALF_NORM2) and `min_norm2`.

fn dot3(a: vec3<f32>, b: vec3<f32>) -> f32 {
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

// The learned normal v / |v| turned toward the camera (.xyz) and the sign applied (.w, +1
// or -1); all zero (.w = 0) where |v|^2 is not finite or below min_norm2, or the mean is
// not finite (the CPU's None).
fn learned_facing_normal(v: vec3<f32>, mean: vec3<f32>) -> vec4<f32> {
    let norm2 = v.x * v.x + v.y * v.y + v.z * v.z;
    if !(finite(norm2) && finite(mean.x) && finite(mean.y) && finite(mean.z))
        || norm2 < u.min_norm2 {
        return vec4<f32>(0.0);
    }
    let len = sqrt(norm2);
    let a = vec3<f32>(v.x / len, v.y / len, v.z / len);
    // glam's normalize_or_zero: times 1 / |d|, or zero where that is not finite and > 0.
    let d = u.cam.xyz - mean;
    let rcp = 1.0 / sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
    var to_cam = vec3<f32>(0.0);
    if finite(rcp) && rcp > 0.0 {
        to_cam = vec3<f32>(d.x * rcp, d.y * rcp, d.z * rcp);
    }
    let facing = a.x * to_cam.x + a.y * to_cam.y + a.z * to_cam.z;
    var sign = 1.0;
    if facing < 0.0 {
        sign = -1.0;
    }
    return vec4<f32>(a.x * sign, a.y * sign, a.z * sign, sign);
}

// shading.rs `LocalFrame`: `normal` as learned_facing_normal (.w = 0: no frame, the
// inputs are zeros with no gradient), the unit view from the mean to the camera and the
// distance, and the unit half vector with |s + v| (.w = 0 where |s + v|^2 is below
// MIN_HALF_NORM2 or not finite: n.h = 0 without gradient).
struct LocalFrame {
    normal: vec4<f32>,
    view: vec3<f32>,
    dist: f32,
    halfway: vec4<f32>,
}

fn local_frame(v: vec3<f32>, mean: vec3<f32>) -> LocalFrame {
    var f: LocalFrame;
    let normal = learned_facing_normal(v, mean);
    if normal.w == 0.0 {
        return f;
    }
    // appearance.rs `view_direction`, as Phi's view code.
    let d = u.cam.xyz - mean;
    let dist = sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
    if !(finite(dist) && dist > 0.0) {
        return f;
    }
    f.normal = normal;
    f.view = vec3<f32>(d.x / dist, d.y / dist, d.z / dist);
    f.dist = dist;
    let s = u.sun_unit.xyz;
    let sum = vec3<f32>(s.x + f.view.x, s.y + f.view.y, s.z + f.view.z);
    let sum2 = dot3(sum, sum);
    if finite(sum2) && sum2 >= u.sun_unit.w {
        let len = sqrt(sum2);
        f.halfway = vec4<f32>(sum.x / len, sum.y / len, sum.z / len, len);
    }
    return f;
}

// `[n.s, n.v, n.h]` of the frame (zeros without one).
fn local_inputs(f: LocalFrame) -> vec3<f32> {
    if f.normal.w == 0.0 {
        return vec3<f32>(0.0);
    }
    let n = f.normal.xyz;
    var nh = 0.0;
    if f.halfway.w != 0.0 {
        nh = dot3(n, f.halfway.xyz);
    }
    return vec3<f32>(dot3(n, u.sun_unit.xyz), dot3(n, f.view), nh);
}

// `local_inputs_backward` for d = dL/d[n.s, n.v, n.h] on a frame (f.normal.w != 0) of the
// Normal row v: dL/dv and dL/dmean, with .w = 1 where all six are finite (else 0: the
// CPU's None, no gradient).
struct LocalGrad {
    d_v: vec4<f32>,
    d_mean: vec3<f32>,
}

fn local_inputs_backward(f: LocalFrame, v: vec3<f32>, d: vec3<f32>) -> LocalGrad {
    let n_hat = f.normal.xyz;
    let uv = f.view;
    let s = u.sun_unit.xyz;
    // dL/d n_hat, n_hat = sign v / |v|.
    var d_n = s * d.x + uv * d.y;
    // dL/d u: through n.v, and through h = (s + u) / |s + u|.
    var d_u = n_hat * d.y;
    if f.halfway.w != 0.0 {
        let h = f.halfway.xyz;
        d_n = d_n + h * d.z;
        d_u = d_u + (n_hat - h * dot3(h, n_hat)) * (d.z / f.halfway.w);
    }
    let v_norm = sqrt(dot3(v, v));
    let n = v / v_norm;
    let d_v = (d_n - n * dot3(n, d_n)) * (f.normal.w / v_norm);
    // u = (c - mean) / |c - mean|: d u / d mean = -(I - u u^T) / r.
    let d_mean = -(d_u - uv * dot3(uv, d_u)) / f.dist;
    var g: LocalGrad;
    let ok = finite(d_v.x) && finite(d_v.y) && finite(d_v.z) && finite(d_mean.x)
        && finite(d_mean.y) && finite(d_mean.z);
    if ok {
        g.d_v = vec4<f32>(d_v, 1.0);
        g.d_mean = d_mean;
    }
    return g;
}
