"""The paper's reported numbers and a "paper vs reflectmm" table (docs/evaluation.md).

Only the numbers the project has checked against the paper's text are recorded; the other cells of its tables
are not copied here (a report shows "—" for them). The paper measures real images (FFHQ-style test images,
3D-RFE Light Stage scans); reflectmm measures the synthetic world with ground truth, so the comparison is of
*trends and magnitudes*, not of equal numbers.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

__all__ = ["PaperNumber", "PAPER_NUMBERS", "paper_vs_ours_rows"]


@dataclass(frozen=True)
class PaperNumber:
    key: str
    table: str
    quantity: str
    value: float
    unit: str
    note: str = ""


PAPER_NUMBERS: tuple[PaperNumber, ...] = (
    PaperNumber("table2.psnr_gain_finetune", "Table 2", "PSNR gain of ours over ours w/o finetuning", 0.95, "dB",
                "in-the-wild test images, face region"),
    PaperNumber("table3.diffuse_psnr", "Table 3", "diffuse albedo PSNR (ours)", 20.13, "dB",
                "3D-RFE Light Stage scans"),
    PaperNumber("table3.specular_psnr", "Table 3", "specular albedo PSNR (ours; Σw as specular albedo)", 19.14,
                "dB", "3D-RFE Light Stage scans"),
)


def paper_vs_ours_rows(ours: Mapping[str, float | None],
                       commands: Mapping[str, str] | None = None,
                       intervals: Mapping[str, float] | None = None) -> list[dict[str, str]]:
    """Rows ``{"table", "quantity", "paper", "reflectmm", "command"}`` for each paper number; ``ours`` maps a
    :class:`PaperNumber` key to the measured value (missing/None → "not run"), ``intervals`` a key to the half
    width of its 95 % confidence interval (written as ``± h`` after the value)."""
    rows = []
    for p in PAPER_NUMBERS:
        v = ours.get(p.key)
        sign = "+" if p.key.endswith("gain_finetune") else ""
        h = (intervals or {}).get(p.key)
        if v is None:
            text = "not run"
        else:
            text = (f"{v:+.2f}" if sign else f"{v:.2f}") + (f" ± {h:.2f}" if h is not None else "") + f" {p.unit}"
        rows.append({"table": p.table, "quantity": p.quantity, "paper": f"{sign}{p.value:.2f} {p.unit}",
                     "reflectmm": text, "command": (commands or {}).get(p.key, "")})
    return rows
