// The networks' list of the Sun-aware resident step: flagged Gaussian i (member[i] = 1: a
// survivor of the projection, or a Gaussian the blend reads) goes to row scanned[i] of the
// list (ascending indices, the CPU's list), and the count (scanned[n], the exclusive prefix
// sum's total) to count[0], where the network kernels read it.

@group(0) @binding(0) var<uniform> c: Count;
@group(0) @binding(1) var<storage, read> member: array<u32>;
@group(0) @binding(2) var<storage, read> scanned: array<u32>;
@group(0) @binding(3) var<storage, read_write> list: array<u32>;
@group(0) @binding(4) var<storage, read_write> count: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i == 0u {
        count[0] = scanned[c.n];
    }
    if i >= c.n {
        return;
    }
    if member[i] != 0u {
        list[scanned[i]] = i;
    }
}
