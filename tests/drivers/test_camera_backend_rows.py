"""Camera backends are rows of the registry (issue 30): ``[sensor.capture]`` is read with
the options model of the row its ``backend`` names, the rig class comes from the row, and
whether mock mode serves the cameras by a twin is the row's say — a new row needs no edit
anywhere else. A backend only mock mode may use is refused in a configuration."""

from __future__ import annotations

import dataclasses
import sys
import types
from typing import Literal

import pytest

import cellcal.families as registry
from cellcal.drivers.cameras.backends import CameraOptions, RigOptions, rig_class
from cellcal.drivers.photogrammetry import CameraRigOptions
from cellcal.mocks.rig.twin import why_no_twin


class PhotoBoothOptions(RigOptions):
    """A made-up backend: cameras behind a photo booth's HTTP API."""

    backend: Literal["photo-booth"] = "photo-booth"
    cameras: list[CameraOptions]
    booth_url: str


class PhotoBoothRig:
    def __init__(self, options: PhotoBoothOptions) -> None:
        self.options = options

    @classmethod
    def from_options(cls, options: PhotoBoothOptions, clock: object = None) -> PhotoBoothRig:
        return cls(options)


@pytest.fixture
def booth(monkeypatch: pytest.MonkeyPatch) -> str:
    module = types.ModuleType("photo_booth_backend")
    module.PhotoBoothOptions = PhotoBoothOptions  # type: ignore[attr-defined]
    module.PhotoBoothRig = PhotoBoothRig  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "photo_booth_backend", module)
    row = registry.CameraBackend(
        "photo-booth",
        "photo_booth_backend:PhotoBoothOptions",
        "photo_booth_backend:PhotoBoothRig",
        None,
        "cameras behind a photo booth's HTTP API",
    )
    monkeypatch.setattr(registry, "CAMERA_BACKENDS", (*registry.CAMERA_BACKENDS, row))
    return row.name


def _sensor(capture: dict[str, object]) -> CameraRigOptions:
    return CameraRigOptions.model_validate(
        {"name": "rig", "rig_file": "rig.toml", "target_file": "target.toml", "capture": capture}
    )


def test_a_new_row_is_read_built_and_served_from_the_table(booth: str) -> None:
    cameras = [{"name": "c0", "address": "http://booth/0"}, {"name": "c1"}]
    options = _sensor({"backend": booth, "cameras": cameras, "booth_url": "http://booth"})
    capture = options.capture
    assert isinstance(capture, PhotoBoothOptions) and capture.booth_url == "http://booth"
    assert capture.camera_names() == ("c0", "c1")
    assert options.endpoint() == "http://booth/0"
    assert rig_class(booth) is PhotoBoothRig
    # no twin in its row: mock mode renders its cameras in-process, and says why
    assert why_no_twin(booth) == 'backend "photo-booth" has no protocol twin'
    with pytest.raises(ValueError, match="booth_url"):
        _sensor({"backend": booth, "cameras": cameras})


def test_what_a_configuration_may_not_name(booth: str) -> None:
    named = "aravis, opencv, files, photo-booth"
    with pytest.raises(
        ValueError, match=f"'rendered' is not a camera backend \\(choose {named}\\)"
    ):
        _sensor({"backend": "rendered", "cameras": [{"name": "c0"}]})
    with pytest.raises(ValueError, match=f"backend: required key missing \\(choose {named}\\)"):
        _sensor({"cameras": [{"name": "c0"}]})


def test_a_row_with_a_twin_is_served_by_it_unless_it_says_why_not(monkeypatch) -> None:
    aravis = registry.camera_backend("aravis")
    assert aravis is not None and aravis.twin is not None
    down = dataclasses.replace(aravis, unavailable="photo_booth_backend:why")
    module = types.ModuleType("photo_booth_backend")
    module.why = lambda: "no GigE Vision here"  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "photo_booth_backend", module)
    others = tuple(b for b in registry.CAMERA_BACKENDS if b.name != "aravis")
    monkeypatch.setattr(registry, "CAMERA_BACKENDS", (down, *others))
    assert why_no_twin("aravis") == "no GigE Vision here"
    monkeypatch.setattr(
        registry, "CAMERA_BACKENDS", (dataclasses.replace(aravis, unavailable=None), *others)
    )
    assert why_no_twin("aravis") is None
