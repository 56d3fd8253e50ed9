//! Tile rasterizer for Gaussians: projection, binning, blending, and the backward pass.
