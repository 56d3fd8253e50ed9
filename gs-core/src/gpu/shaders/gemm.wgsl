// Tiled matrix product C (m x n, row-major) = op(A) op(B) (+ C when accumulate): 16x16
// output tiles, one workgroup each, the reduction dimension staged through workgroup
// memory 16 at a time. op() is expressed by strides: A(i, p) = a[i * a_rs + p * a_cs],
// B(p, j) = b[p * b_rs + j * b_cs], so transposed operands need no copy.

struct Gemm {
    m: u32,
    n: u32,
    k: u32,
    accumulate: u32,
    a_rs: u32,
    a_cs: u32,
    b_rs: u32,
    b_cs: u32,
}

@group(0) @binding(0) var<uniform> g: Gemm;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> c: array<f32>;

var<workgroup> ta: array<f32, 256>;
var<workgroup> tb: array<f32, 256>;

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) l3: vec3<u32>) {
    let row = wid.y * 16u + l3.y;
    let col = wid.x * 16u + l3.x;
    var sum = 0.0;
    for (var t0 = 0u; t0 < g.k; t0 += 16u) {
        let ac = t0 + l3.x;
        var av = 0.0;
        if row < g.m && ac < g.k {
            av = a[row * g.a_rs + ac * g.a_cs];
        }
        ta[l3.y * 16u + l3.x] = av;
        let br = t0 + l3.y;
        var bv = 0.0;
        if br < g.k && col < g.n {
            bv = b[br * g.b_rs + col * g.b_cs];
        }
        tb[l3.y * 16u + l3.x] = bv;
        workgroupBarrier();
        for (var p = 0u; p < 16u; p++) {
            sum += ta[l3.y * 16u + p] * tb[p * 16u + l3.x];
        }
        workgroupBarrier();
    }
    if row < g.m && col < g.n {
        var base = 0.0;
        if g.accumulate != 0u {
            base = c[row * g.n + col];
        }
        c[row * g.n + col] = base + sum;
    }
}
