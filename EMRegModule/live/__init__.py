"""Live navigation in the operating room: the navigator and its watchdog (:mod:`.navigator`), guidance to a plan
(:mod:`.guide`, :mod:`.guide_setup`) and the live recordings (:mod:`.writers`), over the devices of
:mod:`EMRegModule.devices`.

Two terminals::

    emreg sim-tracker --link /tmp/trakstar            # prints: trakSTAR simulator on /dev/pts/N ...
    emreg navigate --registration OUT/registration.json \
        --source trakstar:///tmp/trakstar?baud=115200 --igtl-port 18944 --out OUT

then connect any OpenIGTLink client (3D Slicer's OpenIGTLinkIF: client, localhost, 18944). The
``ProbeToImage`` TRANSFORM is ``ProbeToRAS`` - the pose in 3D Slicer's RAS world, applied as is -
and a STATUS named ``Navigation`` says why poses stop when the watchdog holds them back.
"""
