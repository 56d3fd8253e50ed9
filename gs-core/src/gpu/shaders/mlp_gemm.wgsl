// Matrix products of the device MLP (gpu/mlp.rs): C = op(A) op(B) with C m x n row-major
// and op() by strides, A(i, p) = a[i * a_rs + p * a_cs], B(p, j) = b[p * b_rs + j * b_cs]
// (as gemm.wgsl), the reduction split into chunks of `k_chunk` (split-K): workgroup z
// sums p in [z k_chunk, min(k, (z + 1) k_chunk)) in order into c[z m n + i n + j], and
// mlp_sum_chunks.wgsl adds the chunks in order (the weight gradient's reduction runs over
// every row of a batch; unsplit it would be a few threads each walking all rows).
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
}

@group(0) @binding(0) var<uniform> g: Gemm;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> c: array<f32>;

@compute @workgroup_size(16, 16)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let row = gid.y;
    let col = gid.x;
    if row >= g.m || col >= g.n {
        return;
    }
    let k0 = wid.z * g.k_chunk;
    let k1 = min(g.k, k0 + g.k_chunk);
    var sum = 0.0;
    var ai = row * g.a_rs + k0 * g.a_cs;
    var bi = k0 * g.b_rs + col * g.b_cs;
    for (var p = k0; p < k1; p++) {
        sum += a[ai] * b[bi];
        ai += g.a_cs;
        bi += g.b_rs;
    }
    c[wid.z * g.m * g.n + row * g.n + col] = sum;
}
