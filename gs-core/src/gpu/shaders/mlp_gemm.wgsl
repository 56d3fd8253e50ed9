// Matrix products of the device MLP (gpu/mlp.rs): C = op(A) op(B) with C m x n row-major
// and op() by strides, A(i, p) = a[a_off + i * a_rs + p * a_cs], B(p, j) = b[b_off +
// p * b_rs + j * b_cs] (as gemm.wgsl, plus word offsets so a network's weights are read in
// place from its one flat parameter buffer), the reduction split into chunks of `k_chunk`
// (split-K): workgroup z sums p in [z k_chunk, min(k, (z + 1) k_chunk)) in order into
// c[c_off + z m n + i n + j], and mlp_sum_chunks.wgsl adds the chunks in order (the weight
// gradient's reduction runs over every row of a batch; unsplit it would be a few threads
// each walking all rows).
// The batch's live row count is live[0], read on the device (rows r >= live[0] are dead):
// live_dim 1 says the rows of C are batch rows (dead ones are written 0 and read nothing),
// live_dim 2 that the reduction runs over batch rows (it stops at the live count, so a
// chunk past it writes 0), live_dim 0 that neither is.
// One invocation per output reading straight from storage, no workgroup memory and no
// barriers: on lavapipe this is 3-5x faster than gemm.wgsl's tiled version for the MLPs'
// shapes (barrier-synchronised workgroups are slow there); a GPU may prefer tiles.

struct Gemm {
    m: u32,
    n: u32,
    k: u32,
    k_chunk: u32,
    a_rs: u32,
    a_cs: u32,
    b_rs: u32,
    b_cs: u32,
    a_off: u32,
    b_off: u32,
    c_off: u32,
    live_dim: u32,
}

@group(0) @binding(0) var<uniform> g: Gemm;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> c: array<f32>;
@group(0) @binding(4) var<storage, read> live: array<u32>;

@compute @workgroup_size(16, 16)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let row = gid.y;
    let col = gid.x;
    if row >= g.m || col >= g.n {
        return;
    }
    let at = g.c_off + wid.z * g.m * g.n + row * g.n + col;
    let live_rows = live[0];
    if g.live_dim == 1u && row >= live_rows {
        c[at] = 0.0;
        return;
    }
    let k0 = wid.z * g.k_chunk;
    var k1 = min(g.k, k0 + g.k_chunk);
    if g.live_dim == 2u {
        k1 = min(k1, live_rows);
    }
    var sum = 0.0;
    var ai = g.a_off + row * g.a_rs + k0 * g.a_cs;
    var bi = g.b_off + k0 * g.b_rs + col * g.b_cs;
    for (var p = k0; p < k1; p++) {
        sum += a[ai] * b[bi];
        ai += g.a_cs;
        bi += g.b_rs;
    }
    c[at] = sum;
}
