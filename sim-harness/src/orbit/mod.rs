//! Relative orbit (ROE), two-body reference propagation, Sun ephemeris, Earth shadow, target attitude.
