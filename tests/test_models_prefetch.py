"""The network sessions a plan uses are built ahead on a background thread (Models.prefetch):
the same sessions as built on demand, errors raised where the session is asked for, nothing
left running when a run ends early."""

import threading

import pytest

from relightcli.errors import MissingDependencyError
from relightcli.pipeline import RelightOptions, planned_models
from relightcli.stages.frame import Models


def test_the_default_plan_prefetches_its_nets_in_the_order_they_are_used():
    assert planned_models(RelightOptions()) == [
        "person_detector", "pose_landmarks", "geometry_prior", "ao", "delight",
        "face_detector", "face_mesh", "body_refine", "face_refine"]


@pytest.mark.parametrize("options, families", [
    (RelightOptions(outputs=("normal",)), ["person_detector", "pose_landmarks", "geometry_prior"]),
    (RelightOptions(method="sh9"), ["person_detector", "pose_landmarks", "geometry_prior", "delight"]),
    (RelightOptions(method="raytrace-norefine"),  # no refinement: no AO net either
     ["person_detector", "pose_landmarks", "geometry_prior", "delight"]),
])
def test_a_plan_prefetches_only_the_nets_its_stages_use(options, families):
    assert planned_models(options) == families


def test_the_landmark_lifter_is_prefetched_only_where_the_models_folder_ships_it(monkeypatch):
    from relightcli import pipeline

    assert "lift" not in planned_models(RelightOptions())
    monkeypatch.setattr(pipeline, "_ships", lambda model: True)
    families = planned_models(RelightOptions())
    assert families.index("pose_landmarks") < families.index("lift") < families.index("geometry_prior")


def test_a_prefetched_session_is_the_one_get_returns_and_is_kept():
    models = Models(threads=1)
    models.prefetch(["ao", "face_detector"])
    ao = models.get("ao")
    assert type(ao).__name__ == "AONet" and models.get("ao") is ao
    assert type(models.get("face_detector")).__name__ == "FaceDetector"
    models.stop_prefetch()


def test_a_session_that_fails_to_build_raises_where_it_is_asked_for(monkeypatch):
    def broken(self, family, run_size):
        raise MissingDependencyError(f"model {family!r} is broken", fix="reinstall")

    monkeypatch.setattr(Models, "_create", broken)
    models = Models(threads=1)
    models.prefetch(["delight"])  # no error here: the run goes on until the net is needed
    with pytest.raises(MissingDependencyError, match="'delight' is broken"):
        models.get("delight")


def test_stopping_drops_the_sessions_not_yet_started(monkeypatch):
    started, release, built = threading.Event(), threading.Event(), []

    def slow(self, family, run_size):
        started.set()
        release.wait(10)
        built.append(family)
        return family

    monkeypatch.setattr(Models, "_create", slow)
    models = Models(threads=1)
    models.prefetch(["ao", "delight", "face_mesh"])
    assert started.wait(10)
    models.stop_prefetch()  # "ao" is being built; the other two never start
    release.set()
    assert models.get("ao") == "ao"
    assert models.get("delight") == "delight"  # built on demand, on this thread
    assert built == ["ao", "delight"]


def test_the_light_solves_and_the_tracers_tables_are_filled_ahead_only_when_the_plan_uses_them():
    from relightcli.pipeline import prepared_models
    from relightcli.render.environment import _cosine_kernel_spectrum
    from relightcli.render.inverse import transport_table

    transport_table.cache_clear()
    _cosine_kernel_spectrum.cache_clear()
    models = prepared_models(RelightOptions(outputs=("normal",)))
    models._executor.shutdown(wait=True)  # all it was given: sessions, no table
    assert transport_table.cache_info().currsize == 0 and _cosine_kernel_spectrum.cache_info().currsize == 0
    models = prepared_models(RelightOptions())
    models._executor.shutdown(wait=True)  # sessions, then the tables
    assert transport_table.cache_info().currsize == 1 and _cosine_kernel_spectrum.cache_info().currsize == 1


def test_a_table_that_fails_ahead_does_not_stop_the_sessions():
    def broken():
        raise MemoryError("no room for the table")

    models = Models(threads=1)
    models.prefetch(["ao"], tables=[broken])
    assert type(models.get("ao")).__name__ == "AONet"
    models.stop_prefetch()


def test_the_blas_limits_library_scan_waits_for_the_session_in_hand(monkeypatch):
    """threadpoolctl's scan holds the dynamic loader's lock and calls back into Python: beside a
    thread that loads a library while holding the GIL, both would wait for ever."""
    from relightcli.stages.frame import one_blas_thread

    started, release = threading.Event(), threading.Event()

    def slow(self, family, run_size):
        started.set()
        release.wait(10)
        return family

    monkeypatch.setattr(Models, "_create", slow)
    models = Models(threads=1)
    models.prefetch(["ao"])
    assert started.wait(10)
    scanned = threading.Event()
    scan = threading.Thread(target=lambda: (one_blas_thread(models).restore_original_limits(), scanned.set()))
    scan.start()
    assert not scanned.wait(0.3)  # waits for the build in hand
    release.set()
    assert scanned.wait(10)
    scan.join()


SPY = """
import json, sys, threading
imported = []
class Spy:
    def find_spec(self, name, path=None, target=None):
        if threading.current_thread().name.startswith("relight-models"):
            imported.append(name)
        return None
sys.meta_path.insert(0, Spy())
from relightcli.cli import main
try:
    main(sys.argv[1:])
except SystemExit:
    pass
print("IMPORTED " + json.dumps(imported))
"""


def test_the_prefetch_thread_imports_nothing(tmp_path):
    """An import on that thread can deadlock against threadpoolctl's scan (Models.prefetch): a
    whole run, without a mask (the people stage) and with, records every module first imported
    on it."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for extra in ([], ["--mask", str(root / "examples" / "skier_mask.png")]):
        out = subprocess.run([sys.executable, "-c", SPY, str(root / "examples" / "skier.jpg"), "--hdr",
                              str(root / "examples" / "noon_grass.hdr"), "-o", str(tmp_path / "skier.png"),
                              "--resolution", "128", "--overwrite", *extra],
                             capture_output=True, text=True, timeout=300, cwd=tmp_path)
        line = [x for x in out.stdout.splitlines() if x.startswith("IMPORTED ")]
        assert line, out.stderr[-2000:]
        assert json.loads(line[0][len("IMPORTED "):]) == []
