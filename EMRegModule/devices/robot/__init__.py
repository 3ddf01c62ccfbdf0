"""Robot drivers behind a URL, as the trackers are: :mod:`.driver` (what a robot is to EMReg), :mod:`.url`
(``franka://HOST`` and :func:`~.url.open_robot`), :mod:`.franka` (a Franka FR3 / Panda through the community client
franky-control, libfranka's own network protocol; the optional extra ``robot``). :mod:`.guard` watches the tracker
while the robot moves and stops it.
"""
