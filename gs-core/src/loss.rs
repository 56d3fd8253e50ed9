//! Photometric losses (L1, SSIM) with analytic backward, and metrics (PSNR, SSIM).
