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

Per device, the same three layers: :mod:`.trakstar` and :mod:`.aurora` each hold ``protocol`` (the bytes, with
their sources), ``driver`` (the serial client: pyserial / ndicapi) and ``source`` (the live sample source behind
``trakstar://`` / ``aurora://``). Shared by both: :mod:`.samples` (what a source delivers), :mod:`.source_base`
(what a source is), :mod:`.sources` (replay and OpenIGTLink sources, and ``open_source`` for a URL),
:mod:`.device_url` (``trakstar://``, ``aurora://``, ``igtl://``, ``replay:``), :mod:`.link_quality`,
:mod:`.port_check`, :mod:`.igtl_status` (OpenIGTLink STATUS on pyigtl's message base class), :mod:`.igtl_server` /
:mod:`.igtl_client` (TCP), :mod:`.navigator` (live loop and watchdog), :mod:`.writers` (CSV files flushed every
second). :mod:`.simulator` is both devices on a pseudo-terminal: one pty, one scene, one ``--fault`` grammar, a
protocol emulation per device. :mod:`.commands`: the ``emreg record / sim-tracker / serve`` commands and live
``emreg navigate``.
"""
