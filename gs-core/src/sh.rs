//! Spherical-harmonic colour (degree 0-3) and its backward pass.
