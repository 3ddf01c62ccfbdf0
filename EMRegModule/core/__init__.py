"""The algorithms, pure: arrays and typed settings in, typed results out.

Marker detection in the CT (:mod:`.detection`), frame calibration (:mod:`.calibration`), pairing (:mod:`.pairing`),
the sensor offset (:mod:`.sensor_offset`), registration (:mod:`.registration`, :mod:`.fiducial_registration`), the
error model (:mod:`.error_model`), distortion evidence (:mod:`.distortion`), pivot and tool tips (:mod:`.tool`),
navigation and its checkpoints (:mod:`.navigation`, :mod:`.checkpoints`, :mod:`.slip`), guidance to a plan
(:mod:`.guidance`, :mod:`.plan`), hand-eye and robot targeting (:mod:`.handeye`, :mod:`.handeye_sync`,
:mod:`.robot_target`, :mod:`.robot_motion`, :mod:`.robot_kinematics`), and the shared frames and data model
(:mod:`.transforms`, :mod:`.frames`, :mod:`.tracking`, :mod:`.marker_model`).

Nothing here reads or writes a file, prints, or knows a device or a front end: ``scripts/architecture.py``
checks that ``core`` imports nothing from ``io``, ``devices``, ``live``, ``pipeline`` or the front ends. Progress
is reported through a :class:`~EMRegModule.progress.Progress` passed in. Units are millimetres and degrees unless a
name says otherwise; every pose names its frames (``probe_to_tracker``, ``reference_to_image``).
"""
