// Exclusive prefix sum, stage 1: each workgroup scans 256 values in place and writes the
// block total to `sums[block]`. `sp.x` = length, `sp.y` = number of blocks.

@group(0) @binding(0) var<uniform> sp: vec4<u32>;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> sums: array<u32>;

var<workgroup> tmp: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let block = wid.x + wid.y * nwg.x;
    let i = block * 256u + lid;
    var v = 0u;
    if i < sp.x {
        v = data[i];
    }
    tmp[lid] = v;
    workgroupBarrier();
    for (var off = 1u; off < 256u; off = off * 2u) {
        var add = 0u;
        if lid >= off {
            add = tmp[lid - off];
        }
        workgroupBarrier();
        tmp[lid] = tmp[lid] + add;
        workgroupBarrier();
    }
    if i < sp.x {
        data[i] = tmp[lid] - v;
    }
    if lid == 255u && block < sp.y {
        sums[block] = tmp[255];
    }
}
