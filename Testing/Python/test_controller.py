"""The workflow controller: order of steps, what a new input invalidates."""

from types import SimpleNamespace

import numpy as np
import pytest
import SimpleITK as sitk

from EMRegModule.controller import EMRegController, WorkflowError, WorkflowState
from EMRegModule.errors import EMRegError
from EMRegModule.settings import Settings


def _detection():
    return SimpleNamespace(markers=[object()] * 5, rejected=[])


def _calibration():
    return SimpleNamespace(points=[object()] * 5)


def _registration():
    return SimpleNamespace(reference_to_image=np.eye(4), fre_mm=0.8, sensor_offset_l_mm=14.0)


def test_steps_out_of_order_are_refused_with_what_is_missing():
    controller = EMRegController()
    assert controller.state is WorkflowState.EMPTY
    with pytest.raises(WorkflowError, match="detected markers.*frame calibration"):
        controller.register()
    with pytest.raises(WorkflowError, match="a CT"):
        controller.detect_markers()
    with pytest.raises(WorkflowError, match="calibration recording"):
        controller.calibrate_frame()
    with pytest.raises(WorkflowError, match="registration"):
        controller.navigate_recording(None)
    with pytest.raises(WorkflowError):
        _ = controller.reference_to_image


def test_states_advance_and_new_inputs_invalidate():
    controller = EMRegController()
    controller.set_frame_calibration(_calibration())
    assert controller.state is WorkflowState.FRAME_CALIBRATED
    controller.set_detection(_detection())
    assert controller.state is WorkflowState.READY_TO_REGISTER
    controller.set_registration(_registration())
    assert controller.state is WorkflowState.REGISTERED
    assert "FRE 0.80 mm" in controller.describe()

    # A new CT makes the detection and the registration stale, not the frame calibration.
    controller.set_image(sitk.Image(8, 8, 8, sitk.sitkInt16), "new CT")
    assert controller.detection is None and controller.registration is None
    assert controller.state is WorkflowState.FRAME_CALIBRATED

    controller.set_detection(_detection())
    controller.set_registration(_registration())
    # A new calibration recording drops the frame calibration and the registration.
    controller.set_calibration_recording(SimpleNamespace())
    assert controller.frame_calibration is None and controller.registration is None
    assert controller.state is WorkflowState.MARKERS_DETECTED

    controller.set_frame_calibration(_calibration())
    controller.set_registration(_registration())
    controller.set_sensors(reference_sensor=1, probe_sensor=2)  # unchanged ports keep everything
    assert controller.state is WorkflowState.REGISTERED
    controller.set_sensors(probe_sensor=3)
    assert controller.frame_calibration is None and controller.state is WorkflowState.MARKERS_DETECTED


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
    assert controller.detection is not None
