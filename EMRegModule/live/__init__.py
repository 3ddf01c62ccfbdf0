"""The live operating-room path: trakSTAR serial driver and simulator, OpenIGTLink server/client,
live navigation with a watchdog.

Two terminals::

    emreg sim-tracker --link /tmp/trakstar            # prints: trakSTAR simulator on /dev/pts/N ...
    emreg navigate --registration OUT/registration.json \
        --source trakstar:///tmp/trakstar?baud=115200 --igtl-port 18944 --out OUT

then connect any OpenIGTLink client (3D Slicer's OpenIGTLinkIF: client, localhost, 18944). The
``ProbeToImage`` TRANSFORM is ``ProbeToRAS`` - the pose in 3D Slicer's RAS world, applied as is -
and a STATUS named ``Navigation`` says why poses stop when the watchdog holds them back. For the
real device use ``trakstar:///dev/ttyUSB0?baud=115200``; ``emreg serve --device URL`` publishes the
raw sensors (``ReferenceToTracker``, ``ProbeToTracker``, tracker frame, unchanged) for another
navigator (``--source igtl://HOST:18944``) or PLUS-style clients; ``emreg record --device URL --out
rec.csv`` records the spec's tracking CSV.

Modules: :mod:`.trakstar_protocol` (bytes and words, with their sources), :mod:`.trakstar_driver`
(pyserial client), :mod:`.tracker_simulator` (a trakSTAR on a pseudo-terminal), :mod:`.ndi_protocol`
(NDI's serial API: CRC16, BX/TX/PHSR/PHINF formats, with their sources), :mod:`.aurora_driver` (the
Aurora on ndicapi), :mod:`.aurora_simulator` (an Aurora on a pseudo-terminal), :mod:`.device_url`
(``trakstar://``, ``aurora://``, ``igtl://``, ``replay:``), :mod:`.sources` (sample sources behind those URLs),
:mod:`.igtl_status` (OpenIGTLink STATUS on pyigtl's message base class), :mod:`.igtl_server` /
:mod:`.igtl_client` (TCP), :mod:`.navigator` (live loop and watchdog), :mod:`.writers` (CSV files
flushed every second), :mod:`.commands` (the ``emreg record / sim-tracker / serve`` commands and
live ``emreg navigate``).
"""
