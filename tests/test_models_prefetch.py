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


def test_a_prefetched_session_is_the_one_get_returns_and_is_kept():
    models = Models(threads=1)
    models.prefetch(["ao", "face_detector"])
    ao = models.get("ao")
    assert type(ao).__name__ == "AONet" and models.get("ao") is ao
    assert type(models.get("face_detector")).__name__ == "FaceDetector"
    models.stop_prefetch()


def test_a_session_that_fails_to_build_raises_where_it_is_asked_for(monkeypatch):
    def broken(self, family):
        raise MissingDependencyError(f"model {family!r} is broken", fix="reinstall")

    monkeypatch.setattr(Models, "_create", broken)
    models = Models(threads=1)
    models.prefetch(["delight"])  # no error here: the run goes on until the net is needed
    with pytest.raises(MissingDependencyError, match="'delight' is broken"):
        models.get("delight")


def test_stopping_drops_the_sessions_not_yet_started(monkeypatch):
    started, release, built = threading.Event(), threading.Event(), []

    def slow(self, family):
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


def test_the_light_solves_transport_table_is_filled_ahead_only_when_the_plan_solves():
    from relightcli.pipeline import prepared_models
    from relightcli.render.inverse import transport_table

    transport_table.cache_clear()
    models = prepared_models(RelightOptions(outputs=("normal",)))
    models.get("geometry_prior")  # the last of its sessions: the queue is done
    assert transport_table.cache_info().currsize == 0
    models = prepared_models(RelightOptions())
    models._executor.shutdown(wait=True)  # sessions, then the table
    assert transport_table.cache_info().currsize == 1


def test_a_table_that_fails_ahead_does_not_stop_the_sessions():
    def broken():
        raise MemoryError("no room for the table")

    models = Models(threads=1)
    models.prefetch(["ao"], tables=[broken])
    assert type(models.get("ao")).__name__ == "AONet"
    models.stop_prefetch()
