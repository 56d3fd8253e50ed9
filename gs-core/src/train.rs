//! Vanilla 3DGS training loop over posed images.
