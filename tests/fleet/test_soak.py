"""Issue 30's short soak (about 2 minutes): the daemons of the micro cell on its fakes and through the UR and ABB
protocol simulators, in a fleet with a real PostgreSQL and Mosquitto, run small jobs (a virtual grid, and an
on-board camera calibration that picks and places spheres) while faults fall on a
seeded schedule: device faults drawn by the simulated world, and from outside a kill -9, a plant outage, a
disk-full episode and a wall-clock step, each at least once. Every job is acknowledged and resumed until it is
done, and must then equal an uninterrupted run of its seed; the plant database must hold every record once; the
arm must not move between a fault and the operator's resume. The long soak (500 jobs) is tools/soak.py."""

from __future__ import annotations

import pytest

from tests.support.soak import EXTERNAL, KINDS, Soak, SoakSettings

pytestmark = pytest.mark.long  # run first: see conftest.py


def test_a_short_soak_with_faults_loses_nothing_duplicates_nothing_and_moves_nothing_unasked(
        tmp_path, postgres, mosquitto):
    # seed 9: kill -9 falls on the fake cell's daemon and on the UR one's, whose ur-rtde child must end with it
    settings = SoakSettings(jobs=12, seed=9, job_seeds=(0,), device_faults={
        "link_drop": 0.006, "protective_stop": 0.006, "capture_timeout": 0.006, "corrupt_frame": 0.006,
        "vacuum_loss": 0.03})
    report = Soak(tmp_path, settings, postgres, mosquitto).run()
    print("\n".join(report.lines(warm_up=1)))
    assert report.problems() == []
    assert report.jobs["done"] == settings.jobs and report.jobs["stuck"] == 0
    ran = set(report.faults)
    expected = set(EXTERNAL) - ({"disk_full"} if report.skipped else set())
    assert expected <= ran, (expected, ran)
    assert any(k.startswith("job faulted: ") and k != "job faulted: daemon stopped" for k in ran), ran  # devices
    assert report.jobs["faulted"] >= 2 and report.jobs["resumed"] >= report.jobs["faulted"]
    if "disk_full" in ran:  # the full disk refused a new job, naming the free space and the floor
        assert report.refusals and "24 MB" in report.refusals[0][2] and "free" in report.refusals[0][2]
    assert set(report.lives) == {f"soak-{k}" for k in KINDS}
    assert len(report.lives["soak-fake"]) == len(report.lives["soak-ur"]) == 2 and report.orphans == []
    assert report.latencies  # the readers were answered while the jobs ran
