"""The workflow controller: order of steps, what a new input invalidates, results as values."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.errors import EMRegError
from EMRegModule.pipeline.controller import EMRegController
from EMRegModule.pipeline.results import WorkflowError, WorkflowResults, WorkflowState
from EMRegModule.settings import Settings


def _detection():
    return SimpleNamespace(markers=[object()] * 5, rejected=[])


def _calibration():
    return SimpleNamespace(points=[object()] * 5)


def _registration():
    return SimpleNamespace(reference_to_image=np.eye(4), fre_mm=0.8, sensor_offset_l_mm=14.0)


def test_steps_out_of_order_are_refused_with_what_is_missing():
    controller = EMRegController()
    assert controller.results.state is WorkflowState.EMPTY
    with pytest.raises(WorkflowError, match="detected markers.*frame calibration"):
        controller.make("register")
    with pytest.raises(WorkflowError, match="a CT"):
        controller.make("detect")
    with pytest.raises(WorkflowError, match="calibration recording"):
        controller.make("calibrate")
    with pytest.raises(WorkflowError, match="registration"):
        controller.make("navigate", recording=None)
    with pytest.raises(WorkflowError, match="registration"):
        controller.make("evaluate")
    with pytest.raises(WorkflowError):
        _ = controller.results.reference_to_image


def test_states_advance_and_new_inputs_invalidate():
    controller = EMRegController()
    controller.adopt("calibrate", frame_calibration=_calibration())
    assert controller.results.state is WorkflowState.FRAME_CALIBRATED
    controller.adopt("detect", detection=_detection())
    assert controller.results.state is WorkflowState.READY_TO_REGISTER
    controller.adopt("register", registration=_registration())
    assert controller.results.state is WorkflowState.REGISTERED
    assert "FRE 0.80 mm" in controller.results.describe()

    # A new CT makes the detection and the registration stale, not the frame calibration.
    controller.give(ct=sitk.Image(8, 8, 8, sitk.sitkInt16))
    assert controller.results.detection is None and controller.results.registration is None
    assert controller.results.state is WorkflowState.FRAME_CALIBRATED

    controller.adopt("detect", detection=_detection())
    controller.adopt("register", registration=_registration())
    # A new calibration recording drops the frame calibration and the registration.
    controller.give(calibration=SimpleNamespace())
    assert controller.results.frame_calibration is None and controller.results.registration is None
    assert controller.results.state is WorkflowState.MARKERS_DETECTED

    controller.adopt("calibrate", frame_calibration=_calibration())
    controller.adopt("register", registration=_registration())
    controller.give(sensors=(1, 2))  # unchanged ports keep everything
    assert controller.results.state is WorkflowState.REGISTERED
    controller.give(sensors=(None, 3))
    assert controller.results.frame_calibration is None and controller.results.state is WorkflowState.MARKERS_DETECTED


def test_settings_configure_marker_and_sensors():
    settings = Settings.from_mapping({"sensors": {"reference": 3, "probe": 4}, "marker": {"top_height_mm": 12}})
    controller = EMRegController(settings)
    assert (controller.inputs.reference_sensor, controller.inputs.probe_sensor) == (3, 4)
    assert controller.inputs.marker_model.pinhole_top_mm == pytest.approx(20.5)
    with pytest.raises(TypeError):
        EMRegController({"marker": {"top_height_mm": 12}})  # typed settings only, never a raw dict
    with pytest.raises(EMRegError, match="two different ports"):
        controller.give(sensors=(None, 3))
    assert (controller.inputs.reference_sensor, controller.inputs.probe_sensor) == (3, 4)


def test_bad_image_is_refused_before_anything_changes():
    controller = EMRegController()
    controller.adopt("detect", detection=_detection())
    with pytest.raises(EMRegError, match="3D"):
        controller.give(ct=sitk.Image(8, 8, sitk.sitkInt16))
    assert controller.results.detection is not None and controller.inputs.image is None


def test_the_stage_table_says_what_each_new_result_makes_stale():
    """A new registration drops the navigation and the evaluation made with the old one; a new CT drops the
    markers and everything made from them, not the frame calibration (both from the stage table)."""
    from EMRegModule.stages import DEPENDENTS, outputs_from

    assert DEPENDENTS["register"] == ("navigate", "evaluate", "tre_map", "report", "bundle")
    assert DEPENDENTS["navigate"] == ("report", "bundle")
    assert outputs_from("tre_map") == ["tre_map.nrrd", "report.html", "report_figures", "EMReg.mrb"]
    controller = EMRegController()
    controller.adopt("calibrate", frame_calibration=_calibration())
    controller.adopt("detect", detection=_detection())
    assert controller.results.available(has_image=False, has_calibration_recording=True) == [
        "calibrate", "register", "report"]
    controller.adopt("register", registration=_registration())
    controller.results = controller.results.made("evaluate", evaluation=SimpleNamespace())
    controller.adopt("register", registration=_registration())
    assert controller.results.evaluation is None and controller.results.frame_calibration is not None
    assert "navigate" in controller.results.available(has_image=True, has_calibration_recording=True)


def test_results_are_values_a_new_result_replaces():
    """A result is never changed in place: a stage's new result gives new results (the old ones stay as they were),
    and a field is set only by the stage that makes it."""
    before = WorkflowResults().made("detect", detection=_detection())
    after = before.made("calibrate", frame_calibration=_calibration())
    assert before.frame_calibration is None and after.detection is before.detection
    with pytest.raises(dataclasses.FrozenInstanceError):
        after.registration = _registration()
    with pytest.raises(ValueError, match="register makes registration, not evaluation"):
        after.made("register", evaluation=SimpleNamespace())
    assert after.made("detect", fiducials=SimpleNamespace()).detection is None  # one image side at a time


def test_a_tool_drops_the_frame_calibration_only_when_made_from_its_touches():
    """A new tool maps another tip: the navigation and the evaluation go; a frame calibration made here from the
    old tool's touches goes too, one read from a file stays."""
    controller = EMRegController()
    controller.adopt("calibrate", frame_calibration=_calibration())
    controller.adopt("detect", detection=_detection())
    controller.adopt("register", registration=_registration())
    controller.give(tool="auto")
    assert controller.inputs.tool_auto and controller.results.registration is not None
    controller.results = controller.results.made("calibrate", frame_calibration=_calibration(),
                                                 calibrated_here=True)
    controller.give(tool=None)
    assert not controller.inputs.tool_auto and controller.results.frame_calibration is None
