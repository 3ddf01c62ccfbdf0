"""The workflow controller: order of steps, what a new input invalidates."""

from types import SimpleNamespace

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.errors import EMRegError
from EMRegModule.pipeline.controller import EMRegController
from EMRegModule.pipeline.results import WorkflowError, WorkflowState
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
        controller.register()
    with pytest.raises(WorkflowError, match="a CT"):
        controller.detect_markers()
    with pytest.raises(WorkflowError, match="calibration recording"):
        controller.calibrate_frame()
    with pytest.raises(WorkflowError, match="registration"):
        controller.navigate_recording(None)
    with pytest.raises(WorkflowError):
        _ = controller.results.reference_to_image


def test_states_advance_and_new_inputs_invalidate():
    controller = EMRegController()
    controller.set_frame_calibration(_calibration())
    assert controller.results.state is WorkflowState.FRAME_CALIBRATED
    controller.set_detection(_detection())
    assert controller.results.state is WorkflowState.READY_TO_REGISTER
    controller.set_registration(_registration())
    assert controller.results.state is WorkflowState.REGISTERED
    assert "FRE 0.80 mm" in controller.results.describe()

    # A new CT makes the detection and the registration stale, not the frame calibration.
    controller.set_image(sitk.Image(8, 8, 8, sitk.sitkInt16), "new CT")
    assert controller.results.detection is None and controller.results.registration is None
    assert controller.results.state is WorkflowState.FRAME_CALIBRATED

    controller.set_detection(_detection())
    controller.set_registration(_registration())
    # A new calibration recording drops the frame calibration and the registration.
    controller.set_calibration_recording(SimpleNamespace())
    assert controller.results.frame_calibration is None and controller.results.registration is None
    assert controller.results.state is WorkflowState.MARKERS_DETECTED

    controller.set_frame_calibration(_calibration())
    controller.set_registration(_registration())
    controller.set_sensors(reference_sensor=1, probe_sensor=2)  # unchanged ports keep everything
    assert controller.results.state is WorkflowState.REGISTERED
    controller.set_sensors(probe_sensor=3)
    assert controller.results.frame_calibration is None and controller.results.state is WorkflowState.MARKERS_DETECTED


def test_settings_configure_marker_and_sensors():
    settings = Settings.from_mapping({"sensors": {"reference": 3, "probe": 4}, "marker": {"top_height_mm": 12}})
    controller = EMRegController(settings)
    assert (controller.reference_sensor, controller.probe_sensor) == (3, 4)
    assert controller.marker_model.pinhole_top_mm == pytest.approx(20.5)
    with pytest.raises(TypeError):
        EMRegController({"marker": {"top_height_mm": 12}})  # typed settings only, never a raw dict
    with pytest.raises(EMRegError, match="two different ports"):
        controller.set_sensors(probe_sensor=3)
    assert (controller.reference_sensor, controller.probe_sensor) == (3, 4)


def test_bad_image_is_refused_before_anything_changes():
    controller = EMRegController()
    controller.set_detection(_detection())
    with pytest.raises(EMRegError, match="3D"):
        controller.set_image(sitk.Image(8, 8, sitk.sitkInt16), "slice.png")
    assert controller.results.detection is not None


def test_the_stage_table_says_what_each_new_result_makes_stale():
    """A new registration drops the navigation and the evaluation made with the old one; a new CT drops the
    markers and everything made from them, not the frame calibration (both from the stage table)."""
    from EMRegModule.stages import DEPENDENTS, outputs_from

    assert DEPENDENTS["register"] == ("navigate", "evaluate", "tre_map", "report", "bundle")
    assert DEPENDENTS["navigate"] == ("report", "bundle")
    assert outputs_from("tre_map") == ["tre_map.nrrd", "report.html", "report_figures", "EMReg.mrb"]
    controller = EMRegController()
    controller.set_frame_calibration(_calibration())
    controller.set_detection(_detection())
    assert controller.results.available(has_image=False, has_calibration_recording=True) == [
        "calibrate", "register", "report"]
    controller.set_registration(_registration())
    controller.results.evaluation = SimpleNamespace()
    controller.set_registration(_registration())
    assert controller.results.evaluation is None and controller.results.frame_calibration is not None
    assert "navigate" in controller.results.available(has_image=True, has_calibration_recording=True)
