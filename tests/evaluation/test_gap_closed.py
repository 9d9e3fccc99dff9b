"""The share of the oracle's Table 2 gain that finetuning reaches, and the report's ceiling sentence: a share or a
ceiling only where the oracle's gain is above zero by its confidence interval."""
import numpy as np
import pytest

from reflectmm_cli.evaluation.face_metrics import mean_ci
from reflectmm_cli.evaluation.report import _ceiling_text
from reflectmm_cli.evaluation.tables import gap_sentence, psnr_gap_closed


def _gains(per_image: dict[str, np.ndarray]) -> dict:
    """The gains' summaries as evaluate reconstruction stores them: the mean of the paired PSNR differences with its
    interval, per pair of rows."""
    return {f"{a}{sfx} - initial{sfx}": {"psnr": mean_ci(per_image[a + sfx] - per_image["initial" + sfx])}
            for a in ("finetuned", "oracle") for sfx in ("", "-refined")}


@pytest.fixture()
def psnr():
    rng = np.random.default_rng(3)
    base = rng.normal(15, 1, 40)
    return {"initial": base, "finetuned": base + 0.3 + rng.normal(0, 0.1, 40),
            "oracle": base + 0.6 + rng.normal(0, 0.1, 40),
            "initial-refined": base + 6, "finetuned-refined": base + 6 + rng.normal(0.05, 1.0, 40),
            "oracle-refined": base + 6 + np.tile([0.3, -0.2], 20)}     # mean +0.05, interval ±0.08


def test_the_share_where_the_oracle_gains_and_none_where_its_interval_holds_zero(psnr):
    gains = _gains(psnr)
    enc, ref = gains["oracle - initial"]["psnr"], gains["oracle-refined - initial-refined"]["psnr"]
    assert enc["lo"] > 0 and ref["lo"] <= 0 < ref["mean"]                     # the two cases of the fixture
    gap = psnr_gap_closed(gains, ("finetuned", "initial"), {})
    d_f = np.mean(psnr["finetuned"] - psnr["initial"])
    d_o = np.mean(psnr["oracle"] - psnr["initial"])
    assert gap["encoder-only"] == pytest.approx(d_f / d_o) and np.isnan(gap["refined"])
    text = gap_sentence(gap, ("finetuned", "initial"), gains)
    assert f"encoder-only {100 * d_f / d_o:.0f} %" in text
    assert (f"refined not measured (the oracle's gain, {ref['mean']:+.2f} ± {ref['half_width']:.2f} dB, is not "
            "above zero by its interval)") in text
    # an unequal budget gives no share at all
    assert psnr_gap_closed(gains, ("finetuned", "initial"), {"oracle - initial": ["epochs1 8 against 6"]}) == {}


def test_the_ceiling_names_its_interval_and_says_when_it_holds_zero():
    above = mean_ci(np.array([0.5, 0.7, 0.6, 0.8, 0.55]))
    assert _ceiling_text(above) == f"{above['mean']:+.2f} ± {above['half_width']:.2f} dB"
    around = mean_ci(np.array([0.5, -0.4, 0.3, -0.2, 0.4]))
    assert around["lo"] <= 0 < around["mean"]
    assert _ceiling_text(around).startswith(f"{around['mean']:+.2f} ± {around['half_width']:.2f} dB, an interval "
                                            "that holds zero")
