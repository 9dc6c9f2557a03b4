"""References and metrics: the 2048-sample direct ground truth, path-traced references, FLIP/PSNR/SSIM."""
