"""Virtual twins of the event cameras, served over emulated USB (umockdev).

``usb``: the emulation layer (VirtualUsbBus, EmulatedUsbDevice, run_child, umockdev_available);
``scene_source``: the events a twin streams (a simulated scene or a given array);
``caer_twin``: what the libcaer-protocol twins share; ``dvxplorer`` / ``davis346`` / ``evk4``: the
twins.  Importing this package needs neither umockdev nor gi.
"""

from .usb import (STALL, EmulatedUsbDevice, EndpointSpec, SetupPacket, VirtualUsbBus, run_child,
                  spawn_child, umockdev_available)

__all__ = ["STALL", "EmulatedUsbDevice", "EndpointSpec", "SetupPacket", "VirtualUsbBus",
           "run_child", "spawn_child", "umockdev_available"]
