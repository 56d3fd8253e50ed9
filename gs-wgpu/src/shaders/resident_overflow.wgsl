// Sort capacity check of a forward pass run without the entry-count readback: when the
// scanned total (counts[n]) exceeds the keys the sort ran over, keys were dropped, so the
// step is refused (flags[0] bit 2) and the host redoes it with the exact count.

@group(0) @binding(0) var<uniform> cap: vec4<u32>;
@group(0) @binding(1) var<storage, read> counts: array<u32>;
@group(0) @binding(2) var<storage, read_write> flags: array<atomic<u32>>;

@compute @workgroup_size(1)
fn main() {
    if counts[cap.x] > cap.y {
        atomicOr(&flags[0], 2u);
    }
}
