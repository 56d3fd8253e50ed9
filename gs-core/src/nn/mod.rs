//! Small dense networks: positional encoding, MLP forward/backward on a GEMM.
