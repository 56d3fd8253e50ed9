// Bitonic steps with j <= 256 in workgroup memory: each workgroup owns 512 consecutive
// keys. st.w == 1: sort each block completely (k = 2..512); otherwise run the merge steps
// of stage k = st.x for j = 256 down to 1.

@group(0) @binding(0) var<uniform> st: vec4<u32>;
@group(0) @binding(1) var<storage, read_write> keys: array<vec4<u32>>;

var<workgroup> sh: array<vec4<u32>, 512>;

fn less(a: vec4<u32>, b: vec4<u32>) -> bool {
    return a.x < b.x || (a.x == b.x && (a.y < b.y || (a.y == b.y && a.z < b.z)));
}

fn bitonic_step(base: u32, t: u32, k: u32, j: u32) {
    let i = 2u * j * (t / j) + (t % j);
    let l = i + j;
    let a = sh[i];
    let b = sh[l];
    let up = ((base + i) & k) == 0u;
    if (up && less(b, a)) || (!up && less(a, b)) {
        sh[i] = b;
        sh[l] = a;
    }
}

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let base = (wid.x + wid.y * nwg.x) * 512u;
    let in_range = base < st.z;
    if in_range {
        sh[t] = keys[base + t];
        sh[t + 256u] = keys[base + t + 256u];
    }
    workgroupBarrier();
    if st.w == 1u {
        for (var k = 2u; k <= 512u; k = k * 2u) {
            for (var j = k / 2u; j > 0u; j = j / 2u) {
                bitonic_step(base, t, k, j);
                workgroupBarrier();
            }
        }
    } else {
        for (var j = 256u; j > 0u; j = j / 2u) {
            bitonic_step(base, t, st.x, j);
            workgroupBarrier();
        }
    }
    if in_range {
        keys[base + t] = sh[t];
        keys[base + t + 256u] = sh[t + 256u];
    }
}
