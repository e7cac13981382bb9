"""The docs site builds with --strict, as `tools/docs` builds it: a broken link, a page left out of the nav, a
reference page that cannot be generated, or any other MkDocs warning fails the suite. And the README stays what
a newcomer reads first: short, within 100 columns, its relative links resolving.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MKDOCS = Path(sys.executable).with_name("mkdocs")  # the `docs` extra, which the `test` extra holds: never skipped


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    env.pop("CELLCTL_STORE", None)  # the HTTP reference builds its daemon on a store of its own
    build = subprocess.run([str(MKDOCS), "build", "--strict", "--site-dir", str(out)], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=600)
    return build, out


def test_the_site_builds_with_strict_and_no_warning(site):
    build, out = site
    log = build.stdout + build.stderr
    assert build.returncode == 0, log
    warnings = [line for line in log.splitlines() if re.match(r"\s*(WARNING|ERROR)\b", line)]
    assert not warnings, "\n".join(warnings)
    assert (out / "index.html").exists() and (out / "tutorial" / "simulated-micro-cell.html").exists()


def test_the_reference_pages_are_generated_from_the_code(site):
    """Every verb of the parser, every route of the OpenAPI schema and the cell file's top-level keys are on the
    generated pages, so the reference cannot drift from the code."""
    build, out = site
    assert build.returncode == 0, build.stdout + build.stderr
    from cellctl.cli import build_parser

    cli = (out / "reference" / "cli.html").read_text()
    verbs = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction").choices
    missing = [v for v in verbs if f"cellctl {v}</code>" not in cli]
    assert not missing, f"verbs missing from the CLI reference: {missing}"

    spec = importlib.util.spec_from_file_location("docs_reference_hook", ROOT / "docs" / "hooks" / "reference.py")
    reference = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reference)
    api = (out / "reference" / "http-api.html").read_text()
    paths = reference.openapi_schema()["paths"]
    missing = [p for p in paths if f"<code>{p}</code>" not in api]
    assert not missing, f"routes missing from the HTTP reference: {missing}"

    from cellctl.config import CellFile

    keys = (out / "reference" / "cell-file.html").read_text()
    missing = [k for k in CellFile.model_fields if f"<code>{k}</code>" not in keys]
    assert not missing, f"cell file keys missing from its reference: {missing}"


def test_the_generated_pages_are_not_committed():
    for page in ("cli.md", "http-api.md", "cell-file.md"):
        assert not (ROOT / "docs" / "reference" / page).exists(), f"docs/reference/{page} is generated: remove it"


def test_the_readme_is_short_fits_100_columns_and_its_links_resolve():
    text = (ROOT / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines; the rest belongs in docs/"
    wide = [(n, line) for n, line in enumerate(lines, 1) if len(line) > 100]
    assert not wide, f"README.md lines over 100 columns: {[n for n, _ in wide]}"
    for target in re.findall(r"\]\(([^)]+)\)", text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        path = (ROOT / target.split("#")[0]).resolve()
        assert path.exists(), f"README.md links to {target}, which does not exist"


def test_the_readme_keeps_the_two_set_up_commands():
    text = (ROOT / "README.md").read_text()
    assert "tools/demo" in text and "tools/test" in text
    for tool in ("demo", "test", "docs"):
        assert os.access(ROOT / "tools" / tool, os.X_OK)
