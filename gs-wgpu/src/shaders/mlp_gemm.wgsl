// Matrix products of the device MLP (mlp/): C = op(A) op(B) with C m x n row-major
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
// Each invocation computes an 8 x 8 block of C (a 16 x 16 workgroup covers 128 x 128),
// every output its own in-order sum over p exactly as with one invocation per output,
// reading straight from storage: 16 loads per 64 multiply-adds instead of 128 (on lavapipe
// 6x faster than one output per invocation for Phi's shapes; 4 x 4, 8 x 4 and 16 x 4
// blocks measured slower). No workgroup memory and no barriers: on lavapipe
// barrier-synchronised tiles (gemm.wgsl) are 3-5x slower for the MLPs' shapes than plain
// loads; a GPU may prefer shared-memory tiles.

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

// Stores row `r` of the block (columns col0 .. col0 + 7 below cols_end; lo holds the first
// four), or zeros when the row is dead (r >= live_end).
fn store_row(base: u32, r: u32, rows_end: u32, live_end: u32, col0: u32, cols_end: u32, lo: vec4<f32>, hi: vec4<f32>) {
    if r >= rows_end {
        return;
    }
    let vl = select(vec4<f32>(0.0), lo, r < live_end);
    let vh = select(vec4<f32>(0.0), hi, r < live_end);
    let at = base + r * g.n;
    for (var j = 0u; j < 4u; j++) {
        if col0 + j < cols_end {
            c[at + col0 + j] = vl[j];
        }
        if col0 + 4u + j < cols_end {
            c[at + col0 + 4u + j] = vh[j];
        }
    }
}

@compute @workgroup_size(16, 16)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let row0 = gid.y * 8u;
    let col0 = gid.x * 8u;
    if row0 >= g.m || col0 >= g.n {
        return;
    }
    let rows_end = min(g.m, row0 + 8u);
    let cols_end = min(g.n, col0 + 8u);
    let live_rows = live[0];
    // Rows [row0, live_end) compute, [live_end, rows_end) are dead (written 0).
    var live_end = rows_end;
    if g.live_dim == 1u {
        live_end = clamp(live_rows, row0, rows_end);
    }
    let k0 = wid.z * g.k_chunk;
    var k1 = min(g.k, k0 + g.k_chunk);
    if g.live_dim == 2u {
        k1 = min(k1, live_rows);
    }
    if live_end == row0 {
        k1 = k0;
    }
    // Rows and columns past the block's end (or its live rows) repeat its last one (not
    // stored), so every load stays inside the live extent.
    let last_row = max(live_end, row0 + 1u) - 1u;
    let last_col = cols_end - 1u;
    let cl = vec4<u32>(col0, min(col0 + 1u, last_col), min(col0 + 2u, last_col), min(col0 + 3u, last_col)) * g.b_cs;
    let ch = vec4<u32>(min(col0 + 4u, last_col), min(col0 + 5u, last_col), min(col0 + 6u, last_col), min(col0 + 7u, last_col)) * g.b_cs;
    var a0 = g.a_off + row0 * g.a_rs + k0 * g.a_cs;
    var a1 = g.a_off + min(row0 + 1u, last_row) * g.a_rs + k0 * g.a_cs;
    var a2 = g.a_off + min(row0 + 2u, last_row) * g.a_rs + k0 * g.a_cs;
    var a3 = g.a_off + min(row0 + 3u, last_row) * g.a_rs + k0 * g.a_cs;
    var a4 = g.a_off + min(row0 + 4u, last_row) * g.a_rs + k0 * g.a_cs;
    var a5 = g.a_off + min(row0 + 5u, last_row) * g.a_rs + k0 * g.a_cs;
    var a6 = g.a_off + min(row0 + 6u, last_row) * g.a_rs + k0 * g.a_cs;
    var a7 = g.a_off + min(row0 + 7u, last_row) * g.a_rs + k0 * g.a_cs;
    var bi = g.b_off + k0 * g.b_rs;
    var l0 = vec4<f32>(0.0);
    var h0 = vec4<f32>(0.0);
    var l1 = vec4<f32>(0.0);
    var h1 = vec4<f32>(0.0);
    var l2 = vec4<f32>(0.0);
    var h2 = vec4<f32>(0.0);
    var l3 = vec4<f32>(0.0);
    var h3 = vec4<f32>(0.0);
    var l4 = vec4<f32>(0.0);
    var h4 = vec4<f32>(0.0);
    var l5 = vec4<f32>(0.0);
    var h5 = vec4<f32>(0.0);
    var l6 = vec4<f32>(0.0);
    var h6 = vec4<f32>(0.0);
    var l7 = vec4<f32>(0.0);
    var h7 = vec4<f32>(0.0);
    for (var p = k0; p < k1; p++) {
        let bl = vec4<f32>(b[bi + cl.x], b[bi + cl.y], b[bi + cl.z], b[bi + cl.w]);
        let bh = vec4<f32>(b[bi + ch.x], b[bi + ch.y], b[bi + ch.z], b[bi + ch.w]);
        let x0 = a[a0];
        l0 += x0 * bl;
        h0 += x0 * bh;
        let x1 = a[a1];
        l1 += x1 * bl;
        h1 += x1 * bh;
        let x2 = a[a2];
        l2 += x2 * bl;
        h2 += x2 * bh;
        let x3 = a[a3];
        l3 += x3 * bl;
        h3 += x3 * bh;
        let x4 = a[a4];
        l4 += x4 * bl;
        h4 += x4 * bh;
        let x5 = a[a5];
        l5 += x5 * bl;
        h5 += x5 * bh;
        let x6 = a[a6];
        l6 += x6 * bl;
        h6 += x6 * bh;
        let x7 = a[a7];
        l7 += x7 * bl;
        h7 += x7 * bh;
        a0 += g.a_cs;
        a1 += g.a_cs;
        a2 += g.a_cs;
        a3 += g.a_cs;
        a4 += g.a_cs;
        a5 += g.a_cs;
        a6 += g.a_cs;
        a7 += g.a_cs;
        bi += g.b_rs;
    }
    let base = g.c_off + wid.z * g.m * g.n;
    store_row(base, row0, rows_end, live_end, col0, cols_end, l0, h0);
    store_row(base, row0 + 1u, rows_end, live_end, col0, cols_end, l1, h1);
    store_row(base, row0 + 2u, rows_end, live_end, col0, cols_end, l2, h2);
    store_row(base, row0 + 3u, rows_end, live_end, col0, cols_end, l3, h3);
    store_row(base, row0 + 4u, rows_end, live_end, col0, cols_end, l4, h4);
    store_row(base, row0 + 5u, rows_end, live_end, col0, cols_end, l5, h5);
    store_row(base, row0 + 6u, rows_end, live_end, col0, cols_end, l6, h6);
    store_row(base, row0 + 7u, rows_end, live_end, col0, cols_end, l7, h7);
}
