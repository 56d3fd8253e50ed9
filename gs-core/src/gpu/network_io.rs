//! Input assembly and output scatter of the Sun-aware networks (Phi, Psi) on the device,
//! forward and backward, for the device-resident Sun-aware step. (Work in progress.)
