// Radix sort pass, step 3 of 3: every live key moves to
//   scanned hist[digit * n_blocks + block]   (keys of smaller digits, and of this digit
//                                             in earlier blocks)
// + keys of this digit owned by earlier threads of the block
// + keys of this digit earlier in the thread's own run,
// which is a stable counting sort by the digit. The per-thread digit counts are 16-bit
// fields, two digits per u32 (a block holds 4096 < 65536 keys, so no field carries into
// the next), summed over the threads by an inclusive Hillis-Steele scan.

@group(0) @binding(2) var<storage, read> src: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> hist: array<u32>;
@group(0) @binding(4) var<storage, read_write> dst: array<vec4<u32>>;

// Packed counts: word w of thread t at pre[w * 256 + t] holds digits 2w (low half) and
// 2w + 1 (high half).
var<workgroup> pre: array<u32, 2048>;
var<workgroup> base: array<u32, 16>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let block = wid.x + wid.y * nwg.x;
    if block >= ps.n_blocks {
        return;
    }
    if t < DIGITS {
        base[t] = hist[t * ps.n_blocks + block];
    }
    let live = live_count();
    let start = block * BLOCK + t * PER_THREAD;
    var own: array<u32, 8>;
    for (var j = 0u; j < PER_THREAD; j++) {
        let i = start + j;
        if i < live {
            let d = digit_of(src[i]);
            own[d >> 1u] += 1u << ((d & 1u) * 16u);
        }
    }
    for (var w = 0u; w < 8u; w++) {
        pre[w * 256u + t] = own[w];
    }
    workgroupBarrier();
    for (var s = 1u; s < 256u; s = s * 2u) {
        // Every element assigned in every iteration: a zero-initialised `var` in a loop
        // body is not re-zeroed per iteration by every compiler.
        var v: array<u32, 8>;
        for (var w = 0u; w < 8u; w++) {
            v[w] = 0u;
            if t >= s {
                v[w] = pre[w * 256u + t - s];
            }
        }
        workgroupBarrier();
        for (var w = 0u; w < 8u; w++) {
            pre[w * 256u + t] += v[w];
        }
        workgroupBarrier();
    }
    // Exclusive counts: each half of the inclusive sum is at least the thread's own half,
    // so the packed subtraction borrows nothing across halves.
    var at: array<u32, 8>;
    for (var w = 0u; w < 8u; w++) {
        at[w] = pre[w * 256u + t] - own[w];
    }
    for (var j = 0u; j < PER_THREAD; j++) {
        let i = start + j;
        if i < live {
            let k = src[i];
            let d = digit_of(k);
            let half = (d & 1u) * 16u;
            let rank = (at[d >> 1u] >> half) & 0xffffu;
            dst[base[d] + rank] = k;
            at[d >> 1u] += 1u << half;
        }
    }
}
