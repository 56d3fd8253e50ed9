// One bitonic merge step over the whole key buffer (power-of-two length): compares
// elements i and i ^ j, ascending where (i & k) == 0. Keys compare as (tile, depth bits,
// Gaussian index): all distinct, so the order is unique and equals the CPU's (depth sort
// stable in the Gaussian index, then a stable per-tile scatter).

@group(0) @binding(0) var<uniform> st: vec4<u32>;
@group(0) @binding(1) var<storage, read_write> keys: array<vec4<u32>>;

fn less(a: vec4<u32>, b: vec4<u32>) -> bool {
    return a.x < b.x || (a.x == b.x && (a.y < b.y || (a.y == b.y && a.z < b.z)));
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    let l = i ^ st.y;
    if i >= st.z || l <= i {
        return;
    }
    let a = keys[i];
    let b = keys[l];
    let up = (i & st.x) == 0u;
    if (up && less(b, a)) || (!up && less(a, b)) {
        keys[i] = b;
        keys[l] = a;
    }
}
