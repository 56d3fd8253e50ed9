// Tile ranges: after the sort, tile t owns keys[ranges[t].x .. ranges[t].y] (cleared to
// zero beforehand, so tiles without keys are empty). The padding keys (tile 0xffffffff)
// stay after the sorted live keys and end the list, so the kernel needs no entry count:
// it runs over the sort's n_sort keys.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> ranges: array<vec2<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= fr.n_sort {
        return;
    }
    let t = keys[i].x;
    if t == 0xffffffffu {
        return;
    }
    if i == 0u || keys[i - 1u].x != t {
        ranges[t].x = i;
    }
    if i + 1u == fr.n_sort || keys[i + 1u].x != t {
        ranges[t].y = i + 1u;
    }
}
