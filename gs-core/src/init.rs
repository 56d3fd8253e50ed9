//! Initial Gaussians from a point set or random points in a sphere.
