// Densification statistics on the device (densify.rs `DensifyStats::accumulate`): one
// thread per Gaussian adds this step's NDC 2D-mean gradient norm and visibility count
// and keeps the largest screen radius. Skipped when the step was refused (flags[0]) or
// statistics are off; a non-finite norm or radius skips that Gaussian, as on the CPU.
// stats layout: grad_accum [n] f32 bits, visible_count [n] u32, max_radius_px [n] f32 bits.

@group(0) @binding(0) var<uniform> st: Step;
@group(0) @binding(1) var<storage, read> rows: array<f32>;
@group(0) @binding(2) var<storage, read> splats: array<f32>;
@group(0) @binding(3) var<storage, read> flags: array<u32>;
@group(0) @binding(4) var<storage, read_write> stats: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= st.n || st.accumulate_stats == 0u || flags[0] != 0u {
        return;
    }
    let radius = splats[12u * i + 7u];
    if radius < 0.0 {
        return;
    }
    let norm = rows[st.ostride * i + 11u];
    if !is_finite(norm) || !is_finite(radius) {
        return;
    }
    stats[i] = bitcast<u32>(bitcast<f32>(stats[i]) + norm);
    stats[st.n + i] = stats[st.n + i] + 1u;
    stats[2u * st.n + i] = bitcast<u32>(max(bitcast<f32>(stats[2u * st.n + i]), radius));
}
