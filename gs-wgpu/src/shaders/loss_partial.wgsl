// Totals, stage 1: workgroup g sums pixels [g * sum_chunk, (g + 1) * sum_chunk) of each
// of the 2 NC planes of `maps` (weighted SSIM per channel, then weighted |x - y| per
// channel) in a fixed order (thread-strided sums, then a tree) into
// partials[plane * sum_groups + g].

@group(0) @binding(0) var<uniform> lu: LossUniform;
@group(0) @binding(1) var<storage, read> maps: array<f32>;
@group(0) @binding(2) var<storage, read_write> partials: array<f32>;

var<workgroup> partial: array<f32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let n = lu.width * lu.height;
    let start = wg.x * lu.sum_chunk;
    let end = min(start + lu.sum_chunk, n);
    for (var plane = 0u; plane < 2u * NC; plane++) {
        var acc = 0.0;
        for (var p = start + li; p < end; p += 256u) {
            acc += maps[plane * n + p];
        }
        partial[li] = acc;
        workgroupBarrier();
        for (var stride = 128u; stride > 0u; stride >>= 1u) {
            if li < stride {
                partial[li] += partial[li + stride];
            }
            workgroupBarrier();
        }
        if li == 0u {
            partials[plane * lu.sum_groups + wg.x] = partial[0];
        }
        workgroupBarrier();
    }
}
