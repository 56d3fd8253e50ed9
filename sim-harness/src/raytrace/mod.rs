//! CPU ray tracer: BVH, physically based shading, hard Sun shadows.
