"""Verdicts against the noise floor on data the code was not tuned on (issue 22 item 8):
the false-alarm rate of "above the floor" on clean data at its nominal level over 100
seeds; new seeds and new effects, one of which no library term represents; every verdict
on the bundled examples stated against its floor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.analysis.bands import LEVEL
from symcal.data.dataset import make_dataset
from symcal.report.text import verdict_lines
from symcal.simulation import load_scenario, simulate_run

PROBLEMS = ROOT / "problems"
SCENARIOS = PROBLEMS / "scenarios"
EXAMPLES = ROOT / "examples"


def _data(scenario, seed: int) -> dict[str, symcal.Dataset]:
    return {run: make_dataset(run, "simulated", simulate_run(scenario, run, seed), [])
            for run in ("calibration", "flyby")}


@pytest.mark.slow
def test_false_alarm_rate_of_above_the_floor_is_its_nominal_level() -> None:
    """The implicit platen model on the clean courier (exact but for the readings' noise)
    over 100 new seeds (5000-5099): each dataset is above its 95 % band with probability
    2.5 %, so a seed's verdict says "above the floor" somewhere with probability
    1 - 0.975² = 4.9 %.  Measured: 5 seeds of 100 above, 3 below (before the fly-by's
    band allowed for the estimate's share: 6 and 3); mean χ²/dof 1.008 and 1.003, spread
    0.035 and 0.076 (√(2/ν): 0.045 and 0.070).  The bound is the binomial's 99.8 % point
    (11 of 100), for below-the-floor calls alike."""
    problem = symcal.load_problem(PROBLEMS / "platen_self_calibration_implicit.yaml")
    scenario = load_scenario(SCENARIOS / "courier_platen_clean.yaml")
    above = below = 0
    ratios = []
    for seed in range(5000, 5100):
        result = symcal.solve(problem, _data(scenario, seed))
        verdicts = [t.verdict for t in result.floor_tests]
        above += "above" in verdicts
        below += "below" in verdicts
        ratios += [t.chi2_dof for t in result.floor_tests]
    nominal = 1 - (1 - (1 - LEVEL) / 2) ** 2
    assert nominal == pytest.approx(0.0494, abs=1e-4)
    assert above <= 11 and below <= 11, (above, below)
    # and the statistic is centred where the theory puts it
    assert abs(float(np.mean(ratios)) - 1) < 0.02, np.mean(ratios)


#: Clean data for the bundled explicit problems (the scenarios as their models assume the
#: courier) and the planar arm: problem, scenario, dataset -> run.
CLEAN = {
    "platen": (PROBLEMS / "platen_self_calibration.yaml",
               SCENARIOS / "courier_platen_model.yaml",
               {"calibration": "calibration", "flyby": "flyby"}),
    "dual": (PROBLEMS / "dual_sensor_calibration.yaml", SCENARIOS / "courier_dual_model.yaml",
             {"calibration": "calibration", "flyby": "flyby"}),
    "arm": (EXAMPLES / "planar_arm" / "problem_fixed.yaml",
            EXAMPLES / "planar_arm" / "scenario.yaml",
            {"calibration": "calibration", "validation": "swing"}),
}
#: The most false alarms of 100 seeds a 5 % decision may give: its level plus three
#: binomial standard deviations (5 + 6.5).
ALARMS = 11


def _most(seeds: int, level: float = 0.05) -> int:
    """The most false alarms of ``seeds`` a decision at ``level`` may give: its level plus
    three binomial standard deviations (11 of 100, 8 of 60)."""
    return int(level * seeds + 3 * np.sqrt(seeds * level * (1 - level)))


def _alarms(problem, scenario, runs, seeds) -> tuple[int, dict[str, int]]:
    """How many seeds' results are not at the floor (``at_floor`` False), and how many
    times each dataset was off its own 95 % band."""
    false, off = 0, dict.fromkeys(runs, 0)
    for seed in seeds:
        data = {name: make_dataset(name, "simulated", simulate_run(scenario, run, seed), [])
                for name, run in runs.items()}
        result = symcal.solve(problem, data)
        false += result.at_floor is False
        for t in result.floor_tests:
            off[t.dataset] += t.verdict in ("above", "below")
    return false, off


@pytest.mark.slow
@pytest.mark.parametrize("case", ["platen", "dual", "arm"])
def test_at_floor_is_false_on_clean_data_at_its_nominal_level(case: str) -> None:
    """``at_floor`` is one decision at 95 % for the datasets together (each dataset's band
    at the Šidák level 0.95^(1/2)), so on clean data it is False in 5 % of seeds; each
    dataset's own 95 % band stays as it was.  100 new seeds (6000-6099) per problem, the
    bundled explicit courier problems on the data their models assume (the *_model
    scenarios) and the planar arm (fixed gauges; held out: its swing).

    Measured, at_floor False: platen 7, dual 5, arm 6 of 100 (nominal 5; with the
    per-dataset bands and no family-wise decision, as before: 9, 5 and 9, the held-out
    datasets' bands then being χ²_ν's, which their estimate's share spreads wider: the
    arm's swing fell below it 9 times).  Bound: nominal plus 3 binomial σ (11)."""
    path, scenario_path, runs = CLEAN[case]
    false, off = _alarms(symcal.load_problem(path), load_scenario(scenario_path), runs,
                         range(6000, 6100))
    assert false <= ALARMS, (false, off)
    assert all(count <= ALARMS for count in off.values()), off


def _undeclared(folder: Path) -> Path:
    """The bundled models and problems with every noise declaration removed."""
    import shutil

    shutil.copytree(ROOT / "models", folder / "models")
    shutil.copytree(PROBLEMS, folder / "problems")
    for model in (folder / "models").glob("*.yaml"):
        lines = [ln for ln in model.read_text().splitlines()
                 if not ln.strip().startswith("noise:")]
        model.write_text("\n".join(lines).replace(", noise: 20 urad", "") + "\n")
    return folder / "problems"


@pytest.mark.slow
def test_an_estimated_floor_is_at_its_nominal_level_on_clean_data(tmp_path) -> None:
    """Clean courier data (the implicit platen model is exact on it) and models that
    declare no noise: every floor is estimated by successive differences, and its band is
    the one of the ratio it is (the spread over a floor estimated from the same rows),
    not a known floor's.  60 seeds (7000-7059): at_floor is False in about 5 %.

    Measured on seeds 7000-7099 (the test ran 100 of them until it was cut to 60 for the
    suite's time): 4 False; the calibration off its own band 5 times (3
    above, 2 below), the fly-by 8 times (1 above, 7 below).  The held-out fly-by's test
    counts the estimate's error in its residual (smooth along the line, which successive
    differences do not see), with the estimate's covariance from the floors estimated on
    the calibration rows: before it did (3 False; the fly-by 3 above, 3 below), the
    triad's validation run was above its band in 30 of 100 clean seeds
    (benchmarks/FALSE_ALARMS.md).  The fly-by's 7 below, above its nominal 2.5 %, says the
    share is somewhat overstated here, where the constraints share readings.  Over 200
    seeds (7000-7199) with the earlier test: 14 False (7 %; the normal band before that:
    30, 15 %).  Bound: nominal plus 3 binomial σ (8 of 60)."""
    problems = _undeclared(tmp_path)
    problem = symcal.load_problem(problems / "platen_self_calibration_implicit.yaml")
    scenario = load_scenario(SCENARIOS / "courier_platen_clean.yaml")
    result = symcal.solve(problem, _data(scenario, 7000))
    assert {t.method for t in result.floor_tests} == {"combined"}
    assert {s.noise.method for s in result.statistics if s.noise is not None} == {
        "successive differences"}
    false, off = _alarms(problem, scenario, {"calibration": "calibration", "flyby": "flyby"},
                         range(7000, 7060))
    assert false <= _most(60), (false, off)


@pytest.mark.slow
def test_an_effect_no_library_term_represents_is_above_the_floor() -> None:
    """A tooth pitch 1 % longer than the models' (no candidate of the library is that
    effect), new seeds: calibrated with the implicit (otherwise exact) model, every
    dataset is far above its floor, and the verdict says so in the issue's words (the
    old verdict called such a model quiet when no candidate was significant)."""
    scenario = load_scenario(SCENARIOS / "courier_platen_clean.yaml")
    longer = scenario.overlay({"constants": {"rho": 1.016 * 1.01}})
    problem = symcal.load_problem(PROBLEMS / "platen_self_calibration_implicit.yaml")
    for seed in (901, 902):
        result = symcal.solve(problem, _data(longer, seed))
        assert result.at_floor is False
        lines = verdict_lines(result)
        for test in result.floor_tests:
            assert test.verdict == "above" and test.ratio > 3
            assert f"{test.dataset}: {test.ratio:.3g}× the noise floor (χ²/dof" in "\n".join(
                lines)


@pytest.mark.slow
def test_new_seeds_of_a_harmonic_leave_and_reach_the_floor() -> None:
    """The example's hidden 3rd harmonic on new seeds: the basic model is above the floor
    on both datasets, the revised model (the term added) at it, by the global test."""
    scenario = load_scenario(EXAMPLES / "hidden_effect" / "scenario.yaml")
    basic = symcal.load_problem(EXAMPLES / "hidden_effect" / "problem.yaml")
    revised = symcal.load_problem(EXAMPLES / "hidden_effect" / "problem_revised.yaml")
    at = []
    for seed in (811, 812, 813):
        data = _data(scenario, seed)
        assert [t.verdict for t in symcal.solve(basic, data).floor_tests] == ["above"] * 2
        at += [t.verdict for t in symcal.solve(revised, data).floor_tests]
    assert at.count("at") >= 5, at       # 6 datasets, each inside its band with p = 0.95


@pytest.mark.parametrize("path", [
    PROBLEMS / "platen_self_calibration.yaml",
    pytest.param(PROBLEMS / "platen_self_calibration_implicit.yaml", marks=pytest.mark.slow),
    *(pytest.param(PROBLEMS / f"dual_sensor_calibration{s}.yaml", marks=pytest.mark.slow)
      for s in ("", "_implicit")),
    *(pytest.param(EXAMPLES / "hidden_effect" / f"problem{s}.yaml", marks=pytest.mark.slow)
      for s in ("", "_revised")),
    EXAMPLES / "planar_arm" / "problem_fixed.yaml",
])
def test_every_bundled_verdict_is_stated_against_its_floor(path) -> None:
    """Every bundled problem and example declares its readings' noise: its verdict gives
    each dataset against its floor (never "unknown")."""
    result = symcal.solve(path)
    assert result.problem.weighting == "propagated"
    lines = verdict_lines(result)
    for test in result.floor_tests:
        assert test.method == "propagated" and test.verdict is not None
        line = next(ln for ln in lines if ln.startswith(f"{test.dataset}: "))
        assert "noise floor (χ²/dof" in line and "unknown" not in line
    assert all(s.floor is not None for s in result.statistics)


@pytest.mark.slow
def test_a_reference_only_effect_is_reported_apart() -> None:
    """The interferometer reads 1e-4 long (a common scale error: the platen's angles still
    agree, so g_p is at its floor): the fly-by position against it is above its floor
    (3× measured), following the position; the diagnosis reports it apart as real, not
    calibratable by these constraints, and names the problem that adds constraints."""
    from symcal.report.text import diagnosis_document, diagnosis_verdict, references_apart
    from symcal.revise.diagnose import diagnose

    scenario = load_scenario(SCENARIOS / "courier_platen_clean.yaml")
    data = {}
    for run in ("calibration", "flyby"):
        cols = simulate_run(scenario, run, 21)
        cols["y_ref"] = cols["y_ref"] * 1.0001
        data[run] = make_dataset(run, "simulated", cols, [])
    result = symcal.solve(PROBLEMS / "platen_self_calibration_implicit.yaml", data)
    assert [t.verdict for t in result.floor_tests] == ["at", "at"]
    diag = diagnose(result)
    (apart,) = references_apart(diag)
    assert apart.startswith("flyby position_y vs reference, ")
    assert "varies with p2 (η² = 0.9" in apart or "varies with p4 (η² = 0.9" in apart
    assert apart.endswith("dual_sensor_calibration.yaml in the same folder adds the "
                          "constraints g_x, g_y on the same sensors and can determine it")
    cannot = next(ln for ln in diagnosis_verdict(diag) if ln.startswith("what cannot"))
    assert f"{apart} (real, not calibratable by these constraints: they are at their " \
           "floor)" in cannot
    assert diagnosis_document(diag)["references_apart"] == [apart]


def test_what_is_left_finds_a_variable_and_an_interaction() -> None:
    """Non-parametric: a sinusoid along x over noise at its floor is 100 % of the excess
    along x (within the binning's resolution); a pure interaction (sign(x)·sign(y), no
    structure along either alone) is found along the pair, not along x or y."""
    from symcal.analysis.residuals import Variable, what_is_left

    rng = np.random.default_rng(5)
    n, sigma = 4000, 1.0
    x, y, z = rng.uniform(0, 1, n), rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    variables = [Variable("x", x), Variable("y", y), Variable("z", z)]
    r = sigma * rng.standard_normal(n) + 2.0 * np.sin(2 * np.pi * x)
    (top, *_) = what_is_left(r, variables, sigma**2)
    assert top.variables == ("x",) and 0.9 < top.share < 1.1
    r = sigma * rng.standard_normal(n) + 1.5 * np.sign(x - 0.5) * np.sign(y - 0.5)
    found = what_is_left(r, variables, sigma**2, top=10)
    assert set(found[0].variables) == {"x", "y"} and 0.85 < found[0].share < 1.1
    assert all(f.share < 0.05 for f in found if len(f.variables) == 1)
    # at the floor nothing is left to show
    assert what_is_left(sigma * rng.standard_normal(n), variables, sigma**2) == []


@pytest.mark.slow
def test_minimal_detectable_effect_is_detected_with_its_power() -> None:
    """A term of exactly the stated minimal detectable size, in the direction the data see
    worst, injected into 400 noise draws: the candidates' own F-test at its Bonferroni
    level finds it 80 % of the time (binomial 99 % interval ±5 %)."""
    from symcal.analysis.discovery import Basis, Candidate, Design, test_candidates

    rng = np.random.default_rng(7)
    n, k = 600, 40                                # k candidates share the level
    nuisance = np.column_stack([np.ones(n), rng.normal(size=n)])
    x = np.column_stack([np.sin(np.linspace(0, 20, n)), np.cos(np.linspace(0, 20, n))])
    scales = (0.5e-3, 2e-3)
    others = [rng.normal(size=(n, 1)) for _ in range(k - 1)]
    basis = Basis("harmonic", "v", "h", ("a", "b"), ("", ""), scales=scales)
    filler = Basis("linear", "w", "l", ("c",), ("",), scales=(1e-3,))

    def run(r: np.ndarray) -> list[Candidate]:
        cands = [Candidate("y", basis)] + [Candidate(f"y{i}", filler) for i in range(k - 1)]
        design = Design(r, nuisance, ("o", "s"), ())
        return test_candidates(design, cands, [x, *others], 0.01)

    noise = rng.normal(size=n)
    cand = next(c for c in run(noise) if c.output == "y")
    assert cand.mde is not None
    # the worst direction of the scaled regressor, projected as the test projects it
    q = np.linalg.qr(nuisance)[0]
    xs = (x - q @ (q.T @ x)) * np.asarray(scales)
    w, v = np.linalg.eigh(xs.T @ xs)
    coefficient = v[:, 0] * cand.mde / 1e-3 * np.asarray(scales)
    found = 0
    for _ in range(400):
        r = rng.normal(size=n) + x @ coefficient
        found += next(c for c in run(r) if c.output == "y").significant
    assert 0.75 <= found / 400 <= 0.85, found / 400


def test_very_significant_candidates_are_ranked_by_their_evidence_not_a_tie() -> None:
    """Two candidates whose F-tests' tails both underflow: a product tested beyond the
    simpler term it contains (which the residual holds too), and a linear term along
    most of that simpler term.  Beyond its simpler term the product leaves a fraction of
    what the linear term leaves: by far the stronger evidence, though the sum of squares
    it removes beyond that term is smaller.  With both log p at −inf the tie went to the
    larger sum removed: the linear term, the wrong one."""
    from symcal.analysis.discovery import Basis, Candidate, Design, test_candidates

    rng = np.random.default_rng(3)
    n = 2000
    e, x, w = (rng.normal(size=n) for _ in range(3))
    r = 40.0 * e + 8.0 * x + rng.normal(size=n)
    product = Basis("product", "v", "product", ("a",), ("",), scales=(1e-3,))
    linear = Basis("linear", "w", "linear", ("b",), ("",), scales=(1e-3,))
    cands = [Candidate("y", linear), Candidate("y", product)]
    design = Design(r, np.ones((n, 1)), ("o",), ())
    ranked = test_candidates(design, cands, [(e + 0.6 * w)[:, None], x[:, None]], 0.01,
                             extras=[None, e[:, None]])
    first, second = ranked[0], ranked[1]
    assert first.basis is product and second.basis is linear
    assert first.delta_rss < 0.1 * second.delta_rss     # the smaller sum removed first
    assert first.p_value == 0.0 and second.p_value == 0.0                # both underflow
    assert -np.inf < first.log_p < 2 * second.log_p < -1400
    assert first.significant and second.significant


def test_a_chunks_share_computed_apart_adds_up_to_the_sequential_sums() -> None:
    """The pass's threads compute each chunk's share of an entry's sums without the rows
    before it (``_part``); folded in order they give the sequential sums bit for bit,
    also where the rows before a chunk make some of its rows exact (its variances tiny
    against their mean): there the lead computes that share again."""
    from symcal.analysis.floors import _accumulate, _fits, _fold, _part, _Sums

    rng = np.random.default_rng(5)
    sizes, scales = [300, 257, 1, 400, 64], [1.0, 2.0, 1e-14, 1e-20, 3.0]
    pieces = []
    for n, scale in zip(sizes, scales, strict=True):
        d = scale * rng.uniform(0.5, 2.0, n)
        d[rng.random(n) < 0.1] = 0.0                 # declared exact
        pieces.append((rng.normal(size=n), d, d * 1.1, rng.normal(size=(n, 4)),
                       rng.normal(size=(n, 4))))
    sequential, folded, again = _Sums(), _Sums(), 0
    for r, d, e, j, x in pieces:
        _accumulate(sequential, r, d, e, j, x, spread=True)
        part = _part(r, d, e, j, x, 0.0, spread=True)
        if _fits(part, folded, d):
            _fold(folded, part)
        else:
            again += 1
            _accumulate(folded, r, d, e, j, x, spread=True)
    assert again >= 1          # the tiny chunks are judged against the rows before them
    for name in ("n", "w", "wr2", "wr", "r", "r2", "d", "wd", "exact", "diff2", "last"):
        assert getattr(folded, name) == getattr(sequential, name), name
    for name in ("wj", "wjj", "j", "wxv", "x"):
        np.testing.assert_array_equal(getattr(folded, name), getattr(sequential, name))
    assert sequential.exact > sum(int(np.sum(p[1] == 0)) for p in pieces)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_row_pseudo_inverses_by_cofactors_agree_with_the_eigen_decomposition(n) -> None:
    """Each row's covariance inverted by cofactors (up to 3 × 3) or LAPACK where it is
    clearly regular, by its eigen-decomposition elsewhere: the pseudo-inverse and rank
    that dropping the eigenvalues below EXACT of the largest gives, row by row, for
    regular rows of every scale, rows with an exact reading (singular) and rows whose
    smallest eigenvalue sits just above and just below the cut."""
    from symcal.analysis.row_noise import EXACT, row_pinv

    rng = np.random.default_rng(11 + n)
    rows = []
    for scale in (1e-12, 1.0, 1e9):
        for _ in range(40):
            a = rng.normal(size=(n, n + 2))
            rows.append(scale * a @ a.T)
    for ratio in (0.0, 1e-14, 0.5e-12, 2e-12, 1e-9, 1e-6):    # around and at the cut
        q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        vals = np.linspace(1.0, 2.0, n)
        vals[0] = ratio * vals[-1]
        rows.append((q * vals) @ q.T)
    c = np.array(rows)
    got, rank = row_pinv(c)
    for k, ck in enumerate(c):
        w, v = np.linalg.eigh(ck)
        keep = w > EXACT * max(w.max(), 1e-300)
        want = (v[:, keep] / w[keep]) @ v[:, keep].T
        assert rank[k] == keep.sum(), k
        np.testing.assert_allclose(got[k], want, rtol=1e-6,
                                   atol=1e-9 * np.abs(want).max(), err_msg=str(k))
    assert rank.min() < n                       # the singular rows were there
