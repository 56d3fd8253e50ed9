// Radix sort pass, step 1 of 3: each block's digit histogram, written digit-major
// (hist[digit * n_blocks + block]) so that one exclusive prefix sum over the whole array
// gives every (digit, block) its first output position. Blocks past the live keys write
// zeros. The workgroup sums are integer atomics: the same totals in any order.

@group(0) @binding(2) var<storage, read> src: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read_write> hist: array<u32>;

var<workgroup> bins: array<atomic<u32>, 16>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let block = wid.x + wid.y * nwg.x;
    if block >= ps.n_blocks {
        return;
    }
    if t < DIGITS {
        atomicStore(&bins[t], 0u);
    }
    workgroupBarrier();
    let live = live_count();
    let start = block * BLOCK + t * PER_THREAD;
    var c: array<u32, 16>;
    for (var j = 0u; j < PER_THREAD; j++) {
        let i = start + j;
        if i < live {
            let d = digit_of(src[i]);
            c[d] += 1u;
        }
    }
    for (var d = 0u; d < DIGITS; d++) {
        if c[d] != 0u {
            atomicAdd(&bins[d], c[d]);
        }
    }
    workgroupBarrier();
    if t < DIGITS {
        hist[t * ps.n_blocks + block] = atomicLoad(&bins[t]);
    }
}
