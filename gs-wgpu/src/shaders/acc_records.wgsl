// Deterministic backward: one record of REC values per tile entry `e`, written once by
// the tile that owns the entry (no atomics); gather.wgsl sums them per Gaussian in tile
// order.
@group(0) @binding(7) var<storage, read_write> acc: array<f32>;

fn acc_add(i: u32, v: f32) {
    acc[i] = v;
}

fn slot(g: u32, e: u32) -> u32 {
    return e * REC;
}
