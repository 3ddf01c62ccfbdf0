"""The live operating-room path: trakSTAR serial driver and simulator, OpenIGTLink server/client,
live navigation with a watchdog.

Modules: :mod:`.trakstar_protocol` (bytes and words, with their sources), :mod:`.trakstar_driver`
(pyserial client), :mod:`.tracker_simulator` (a trakSTAR on a pseudo-terminal), :mod:`.device_url`
(``trakstar://``, ``igtl://``, ``replay:``), :mod:`.sources` (sample sources behind those URLs),
:mod:`.igtl_status` (OpenIGTLink STATUS on pyigtl's message base class), :mod:`.igtl_server` /
:mod:`.igtl_client` (TCP), :mod:`.navigator` (live loop and watchdog), :mod:`.commands` (the
``emreg record / sim-tracker / serve`` commands and live ``emreg navigate``).
"""
