// Radix sort pass, step 2 of 3: exclusive prefix sum of the DIGITS * n_blocks block
// histograms, in place, by a single workgroup: each thread sums a contiguous run, the
// run totals are scanned in workgroup memory, then each thread rewrites its run.

@group(0) @binding(2) var<storage, read_write> hist: array<u32>;

var<workgroup> sh: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32) {
    let len = DIGITS * ps.n_blocks;
    let per = (len + 255u) / 256u;
    let lo = min(t * per, len);
    let hi = min(lo + per, len);
    var own = 0u;
    for (var i = lo; i < hi; i++) {
        own += hist[i];
    }
    sh[t] = own;
    workgroupBarrier();
    for (var s = 1u; s < 256u; s = s * 2u) {
        var v = 0u;
        if t >= s {
            v = sh[t - s];
        }
        workgroupBarrier();
        sh[t] += v;
        workgroupBarrier();
    }
    var run = sh[t] - own;
    for (var i = lo; i < hi; i++) {
        let h = hist[i];
        hist[i] = run;
        run += h;
    }
}
