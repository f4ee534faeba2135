"""Suite-wide fixtures: keep the suite's disk footprint to one module's worth of captures.

A full run writes ~1.3 GB of captures, transport matrices and renders under pytest's base temporary folder; on a
machine with a small /tmp that ran out of space (CI, stop 57: "No space left on device" at test 598 of 729). Each
passed test's ``tmp_path`` is removed by ``tmp_path_retention_policy = "failed"`` (pyproject.toml); the folders that
module-scoped fixtures make with ``tmp_path_factory`` are removed here once their module is done, unless one of its
tests failed (then they stay for a look). Session-scoped fixtures, whose folders other modules may still read, name
theirs ``session_*`` and are left to pytest's own clean-up.
"""

from __future__ import annotations

import shutil

import pytest


@pytest.fixture(scope="module", autouse=True)
def _remove_module_folders(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    """Delete the base-temp folders made while this module ran, once it is done and if none of its tests failed."""
    base = tmp_path_factory.getbasetemp()
    before = {p.name for p in base.iterdir()}
    failed_before = request.session.testsfailed
    yield
    if request.session.testsfailed != failed_before:
        return
    for folder in base.iterdir():
        if folder.name not in before and folder.is_dir() and not folder.name.startswith("session_"):
            shutil.rmtree(folder, ignore_errors=True)
