// Totals, stage 2: one workgroup sums each plane's partial sums (loss_partial.wgsl) in a
// fixed order (thread-strided, then a tree), so the result is the same bits on every
// run. totals[0]: SSIM, totals[1]: L1 (channel totals added in channel order, as loss.rs
// does).

@group(0) @binding(0) var<uniform> lu: LossUniform;
@group(0) @binding(1) var<storage, read> partials: array<f32>;
@group(0) @binding(2) var<storage, read_write> totals: array<f32>;

var<workgroup> partial: array<f32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) li: u32) {
    var ssim_total = 0.0;
    var l1_total = 0.0;
    for (var plane = 0u; plane < 2u * NC; plane++) {
        var acc = 0.0;
        for (var j = li; j < lu.sum_groups; j += 256u) {
            acc += partials[plane * lu.sum_groups + j];
        }
        partial[li] = acc;
        workgroupBarrier();
        for (var stride = 128u; stride > 0u; stride >>= 1u) {
            if li < stride {
                partial[li] += partial[li + stride];
            }
            workgroupBarrier();
        }
        let channel_total = partial[0];
        workgroupBarrier();
        if plane < NC {
            ssim_total += channel_total;
        } else {
            l1_total += channel_total;
        }
    }
    if li == 0u {
        totals[0] = ssim_total;
        totals[1] = l1_total;
    }
}
