// Prepended to the input-assembly kernels (netio_phi_input, netio_psi_input), after
// netio_common.wgsl: their shared bindings (the packed parameters, the input rows, the
// flags) and the rows without a Gaussian.

@group(0) @binding(3) var<storage, read> params: array<f32>;
@group(0) @binding(4) var<storage, read_write> input: array<f32>;
@group(0) @binding(5) var<storage, read_write> flags: array<atomic<u32>>;

// The Gaussian of row r (< n), or n when the row has none: then the row is written as
// zeros, and a live row's out-of-range list entry sets flags[0] bit 0.
fn input_row_gaussian(r: u32) -> u32 {
    let g = listed_gaussian(r);
    if g >= u.n {
        if is_live(r) {
            atomicOr(&flags[0], 1u);
        }
        let base = r * u.width;
        for (var c = 0u; c < u.width; c++) {
            input[base + c] = 0.0;
        }
    }
    return g;
}
