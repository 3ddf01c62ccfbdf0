"""Simulated trackers on pseudo-terminals, byte-exact to their protocols: :mod:`.pty` (the pty, its link, the
serving loop, the faults every device shares), :mod:`.scene` (what the sensors do, in the Tracker frame),
:mod:`.faults` (the one ``--fault`` grammar), :mod:`.tracker_flags` (the distortion and volume flags a tracker
reports), and the device emulations :mod:`.trakstar` and :mod:`.aurora`.
"""
