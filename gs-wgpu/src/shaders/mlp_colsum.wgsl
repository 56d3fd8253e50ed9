// Bias gradient of the device MLP (mlp/), split over rows like the weight gradient: thread
// (j, z) writes dst[dst_off + z * n + j] = the sum, in row order, of src[r * n + j] over the
// rows r of chunk z, [z chunk_rows, (z + 1) chunk_rows), below min(rows, live[0]) (the live
// count read on the device; a chunk past it writes 0). mlp_sum_chunks.wgsl adds the chunks
// in chunk order (deterministic). One chunk spanning every row is the plain column sum.
// Why chunks: one thread walking all rows of a 100K-row batch is a chain of 100K dependent
// loads; on an H200 that made the networks' backward 40x their forward.

struct ColSum {
    rows: u32,
    n: u32,
    dst_off: u32,
    chunk_rows: u32,
}

@group(0) @binding(0) var<uniform> u: ColSum;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;
@group(0) @binding(3) var<storage, read> live: array<u32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let j = gid.x;
    if j >= u.n {
        return;
    }
    let z = wid.y;
    let end = min(min(u.rows, live[0]), (z + 1u) * u.chunk_rows);
    var sum = 0.0;
    for (var r = z * u.chunk_rows; r < end; r++) {
        sum += src[r * u.n + j];
    }
    dst[u.dst_off + z * u.n + j] = sum;
}
