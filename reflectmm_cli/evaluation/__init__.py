"""Evaluation: image metrics in the face region, errors against ground truth, the representation comparison
(the paper's Table 1 on our own data) and the closing report of a recipe run. See docs/model.md."""
from .metrics import DISPLAY_GAMMA, LPIPS, encode_for_metrics, load_lpips, lpips_distance, psnr, ssim

__all__ = ["DISPLAY_GAMMA", "LPIPS", "encode_for_metrics", "load_lpips", "lpips_distance", "psnr", "ssim"]
