// Shared by the radix sort kernels (sort_radix_*.wgsl): one pass sorts the keys stably by
// a 4-bit digit, bits `shift .. shift + 4` of word `key_word` of each vec4<u32> key. Only
// the first `live_count()` keys take part (the live count is read on the device, clamped
// to the buffer's n_sort keys); keys past it are neither read nor written.
// A block of BLOCK = 256 * PER_THREAD consecutive keys belongs to one workgroup; thread t
// owns the PER_THREAD consecutive keys from t * PER_THREAD, so a block's key order is
// (thread, then position in the thread's run).

struct Pass {
    key_word: u32,
    shift: u32,
    n_blocks: u32,
    n_sort: u32,
    count_word: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

const PER_THREAD: u32 = 16u;
const BLOCK: u32 = 4096u;
const DIGITS: u32 = 16u;

@group(0) @binding(0) var<uniform> ps: Pass;
@group(0) @binding(1) var<storage, read> count: array<u32>;

fn live_count() -> u32 {
    return min(count[ps.count_word], ps.n_sort);
}

fn digit_of(k: vec4<u32>) -> u32 {
    return (k[ps.key_word] >> ps.shift) & 15u;
}
