// Radix sort, after an odd number of passes: the live keys back from the temporary
// buffer into the sorted buffer (the keys past them, padding, stay as they were).

@group(0) @binding(2) var<storage, read> src: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read_write> dst: array<vec4<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i < live_count() {
        dst[i] = src[i];
    }
}
