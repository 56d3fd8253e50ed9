// Gradient accumulator without f32 atomics: f32 bit patterns in atomic<u32>, added with
// a compare-and-swap loop (retries only while another invocation changed the value).
@group(0) @binding(7) var<storage, read_write> acc: array<atomic<u32>>;

fn acc_add(i: u32, v: f32) {
    var old = atomicLoad(&acc[i]);
    loop {
        let r = atomicCompareExchangeWeak(&acc[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}

// Accumulator row of Gaussian `g` (one per Gaussian, shared by all its tile entries).
fn slot(g: u32, e: u32) -> u32 {
    return g * REC;
}
