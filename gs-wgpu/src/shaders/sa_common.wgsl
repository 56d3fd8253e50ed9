// Shared by the Sun-aware resident step's own kernels (resident_sunaware/): a
// uniform holding one count (Gaussians, pixels or values), padded to 16 bytes.

struct Count {
    n: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}
