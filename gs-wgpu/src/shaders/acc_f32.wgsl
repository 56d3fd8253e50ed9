// Gradient accumulator with native f32 atomics (SHADER_FLOAT32_ATOMIC).
@group(0) @binding(7) var<storage, read_write> acc: array<atomic<f32>>;

fn acc_add(i: u32, v: f32) {
    atomicAdd(&acc[i], v);
}

// Accumulator row of Gaussian `g` (one per Gaussian, shared by all its tile entries).
fn slot(g: u32, e: u32) -> u32 {
    return g * REC;
}
