"""The web operator's tests share: the VR cell with a web operator, its requests awaited, the truth of a click."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import numpy as np
import yaml

from drivers.sim.kinds import build_world

from cellctl.config import load_cell_file
from cellctl.core.runs import with_seed

from tests.support.daemon import ROOT, DaemonProcess
from tests.support.wait import eventually

CELL = ROOT / "config" / "sim-vr.yaml"


OFFSET = {"initial_offset_in": [4.0, -2.5, 2.0], "initial_turn_deg": [3.0, -2.0, 4.0]}  # 5.1 in off, as test_vr


CLICK_SIGMA_PX = 2.0


def write_vr_cell(folder: Path, **operator_options) -> Path:
    data = yaml.safe_load(CELL.read_text())
    data["operator"] = {"backend": "web", **operator_options}
    data["store_dir"] = str(folder / "store")
    path = folder / "cell.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path



def pending(client: httpx.Client) -> dict | None:
    return client.get("/operator/request").json()["request"]


def next_request(client: httpx.Client, after: int = 0, job: int | None = None) -> dict:
    def probe():
        req = pending(client)
        if req is None and job is not None:
            state = client.get(f"/jobs/{job}").json()
            assert state["state"] in ("queued", "running"), state
        return req if req is not None and req["id"] > after else None

    return eventually(probe, every=0.05, what=f"an operator request after {after}")


class Truth:
    """The simulated world of a job, rebuilt in the test from its cell file and seed: what the operator sees."""

    def __init__(self, cell_file: Path, seed: int | None):
        config, _ = load_cell_file(cell_file)
        self.world = build_world(with_seed(config, seed).sim)
        self.rng = np.random.default_rng(0)

    def visible(self, req: dict) -> list[int]:
        """The model points the operator can see in this view (all of them, well spread first)."""
        model = self.world.model_solids[req["object"]].vertices
        return [k for k, _, _ in self.world.clicks(req["camera"], req["object"], model, 1, at_most=len(model))]

    def pixels(self, req: dict) -> np.ndarray:
        """Where the real object's points are in the image (before any noise)."""
        cam, obj = self.world.cameras[req["camera"]], req["object"]
        M = self.world.object_pose(obj)
        return cam.project(self.world.solids[obj].vertices @ M[:3, :3].T + M[:3, 3])

    def clicks(self, req: dict, at_most: int = 8) -> list[dict]:
        uv = self.pixels(req)
        noisy = uv + self.rng.normal(0, CLICK_SIGMA_PX, uv.shape)
        return [{"model_index": k, "u": float(noisy[k, 0]), "v": float(noisy[k, 1])} for k in self.visible(req)[:at_most]]


def operator_events(daemon: DaemonProcess, job: int, want: int, timeout: float = 30.0) -> list[dict]:
    """The `operator` events of a job from /events (replayed from the start), until `want` of them came."""
    seen: list[dict] = []
    with httpx.Client(base_url=daemon.url, timeout=httpx.Timeout(timeout)) as c:
        with c.stream("GET", "/events", params={"since": 0, "job": job}) as stream:
            kind = None
            for line in stream.iter_lines():
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: ") and kind == "operator":
                    seen.append(json.loads(line[6:]))
                    if len(seen) >= want:
                        break
    return seen
