//! The standard 3DGS PLY model file (binary little-endian).
