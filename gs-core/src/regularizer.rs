//! Geometric regularisers: the isotropic scale loss.
