// Refuses the step (flags[0] bit 0) when any of the first `len` values of `data` is NaN or
// infinite: the Sun-aware resident step's check of its channels and of every gradient
// before Adam, as the CPU trainer's `first_non_finite` checks.

@group(0) @binding(0) var<uniform> u: Count;
@group(0) @binding(1) var<storage, read> data: array<f32>;
@group(0) @binding(2) var<storage, read_write> flags: array<atomic<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= u.n {
        return;
    }
    if !is_finite(data[i]) {
        atomicOr(&flags[0], 1u);
    }
}
