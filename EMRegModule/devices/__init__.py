"""The devices: the NDI/Ascension trakSTAR and NDI Aurora serial trackers, the Franka robot, their simulators, and
OpenIGTLink (server and client), each behind one small interface.

A tracker is a sample source (:class:`.source_base.SampleSource`: ``start``/``stop``, a callback per
:class:`.samples.SensorSample`) opened from a URL (:func:`.sources.open_source`: ``trakstar://``, ``aurora://``,
``igtl://``, ``replay:``); a robot is a :class:`.robot.driver.RobotDriver` opened from ``franka://``. Per tracker,
three layers: ``protocol`` (the bytes, with their sources), ``driver`` (the serial client) and ``source``.
:mod:`.simulator` is both trackers on a pseudo-terminal, speaking their protocols byte for byte.
"""
