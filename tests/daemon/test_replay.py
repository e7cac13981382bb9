"""Why the daemon replays a simulated run before resuming it on a fresh world.

A restarted daemon builds its simulated world afresh from the seed. The per-step noise
keying (World.begin_step) makes each step's noise reproducible, but not the world's
state: the spheres placed by earlier steps, the arm's position, the clock. A routine
that places spheres then measures a different world after the restart; replaying the
persisted steps first (collect(replay_sim=True)) restores that state exactly.
"""

from __future__ import annotations

import pytest

from cellctl.config import load_cell_file
from cellctl.core.orchestrator import Aborted, JobControl, ReplayMismatch
from cellctl.core.runs import run_routine
from cellctl.stores.run_folder import RunFolder

from tests.support.daemon import ROOT

BOOKKEEPING = ("cell_time_s", "image", "step_rows")
# without camera 1's check of each picked sphere (the cell file's centring_area: area1 needs an active cam1):
# the spheres this routine places are what the replay must restore
AREA2 = {"centring_area": None}


def cut_and_resume(config, text, out, at: int, replay: bool) -> dict:
    control = JobControl()

    def abort_at(p):
        if p.done == at:
            control.abort()

    with pytest.raises(Aborted):
        run_routine("virtual-grid-area2", config, text, out, seed=3, overrides=AREA2, control=control,
                    on_progress=abort_at)
    # a new run_routine builds a new Cell: a fresh world, as after kill -9 and a restart
    return run_routine("virtual-grid-area2", config, text, out, seed=3, overrides=AREA2, resume=True,
                       replay_sim=replay)


def differing(a: list[dict], b: list[dict]) -> int:
    return sum(repr(ra[k]) != repr(rb[k]) for ra, rb in zip(a, b) for k in ra if k not in BOOKKEEPING) \
        + abs(len(a) - len(b))


def test_placed_spheres_are_restored_by_replay(tmp_path):
    config, text = load_cell_file(ROOT / "config" / "sim-microcell.yaml")
    whole = run_routine("virtual-grid-area2", config, text, tmp_path / "whole", seed=3, overrides=AREA2)
    reference = RunFolder(tmp_path / "whole").samples()

    replayed = cut_and_resume(config, text, tmp_path / "replayed", at=9, replay=True)
    samples = RunFolder(tmp_path / "replayed").samples()
    assert differing(reference, samples) == 0
    assert [r["cell_time_s"] for r in samples] == [r["cell_time_s"] for r in reference]
    assert replayed["stats"] == whole["stats"] and replayed["cell_time_s"] == whole["cell_time_s"]

    # without the replay the spheres placed before the cut are missing: the measurements differ
    plain = cut_and_resume(config, text, tmp_path / "plain", at=9, replay=False)
    assert differing(reference, RunFolder(tmp_path / "plain").samples()) > 0
    assert plain["stats"] != whole["stats"]


def test_a_replay_that_does_not_reproduce_the_samples_is_refused(tmp_path):
    """Persisted samples from another world (here: edited) cannot be resumed exactly: say so, move nothing more."""
    config, text = load_cell_file(ROOT / "config" / "sim-microcell.yaml")
    small = {"rows": 4, "cols": 4, "n_verify": 8, "passes": 1}
    control = JobControl()

    def abort_at(p):
        if p.done == 5:
            control.abort()

    with pytest.raises(Aborted):
        run_routine("virtual-grid", config, text, tmp_path / "r", seed=5, overrides=small, control=control,
                    on_progress=abort_at)
    path = RunFolder(tmp_path / "r").samples_path
    lines = path.read_text().splitlines(keepends=True)
    header = lines[0].split(",")
    row = lines[3].split(",")
    row[header.index("u_px")] = "1.5"
    lines[3] = ",".join(row)
    path.write_text("".join(lines))
    with pytest.raises(ReplayMismatch, match="step 2"):
        run_routine("virtual-grid", config, text, tmp_path / "r", seed=5, overrides=small, resume=True,
                    replay_sim=True)
