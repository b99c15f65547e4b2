"""A camera's codec kernels load before its stream flows: the driver's decoder at ``start()``
(``Device.warm_up``), a twin's encoder when the twin is made. Their first call in a process
costs ~0.5 s (seconds on a loaded machine); inside a USB handler or a recording's first
transfers it stalled the stream and cut a 1.5 s recording to its first two events (CI).

Each case runs in a fresh process (kernels already loaded by other tests would hide a miss) and
checks that a realistic chunk, encoded as the twin does and decoded as the driver does after
the warm-up, loads no kernel the warm-up had not."""

import json
import subprocess
import sys

import pytest

CHECK = r"""
import json, sys
import numpy as np
from numba.core.registry import CPUDispatcher
from evdnerf_ros.events.types import EVENT_DTYPE, TRIGGER_DTYPE

def loaded():
    out = {}
    for name, mod in list(sys.modules.items()):
        if name.startswith(("evdnerf_ros", "rig")):
            for k, v in list(vars(mod).items()):
                if isinstance(v, CPUDispatcher):
                    out[f"{name}.{k}"] = len(v.overloads)
    return out

model = sys.argv[1]
rng = np.random.default_rng(0)
n = 500
ev = np.zeros(n, EVENT_DTYPE)
ev["t"] = np.sort(rng.integers(1, 20_000, n)) * 1000
ev["x"], ev["y"] = rng.integers(0, 200, n), rng.integers(0, 100, n)
ev["p"] = rng.choice([-1, 1], n)
if model == "evk4":
    from rig.camera.evk4 import EVK4 as Driver
    from rig.camera.virtual.evk4 import VirtualEVK4 as Twin
    from evdnerf_ros.events.codecs import make_encoder
    encoder = lambda: make_encoder("evt3")
elif model == "dvxplorer":
    from rig.camera.dvxplorer import DVXplorer as Driver
    from rig.camera.virtual.dvxplorer import VirtualDVXplorer as Twin
    from rig.camera.caer_words import CaerWordEncoder
    encoder = lambda: CaerWordEncoder(Driver.width, Driver.height, "DVXplorer")
else:
    from rig.camera.davis346 import DAVIS346 as Driver
    from rig.camera.virtual.davis346 import VirtualDAVIS346 as Twin
    from rig.camera.davis_words import DavisWordEncoder
    encoder = lambda: DavisWordEncoder(Driver.width, Driver.height, "DAVIS346")
from rig.camera.virtual.scene_source import GivenEvents

twin = Twin(GivenEvents(ev, Twin.width if hasattr(Twin, "width") else Driver.width,
                        Twin.height if hasattr(Twin, "height") else Driver.height))
after_twin = loaded()
data = encoder().encode(ev)                 # what the twin's first transfer encodes
after_encode = loaded()
driver = Driver()
driver.warm_up()
after_warm = loaded()
events, _ = driver._decode(data)            # what the driver's first transfer decodes
if driver.encoding == "libcaer":
    from rig.camera.dvxplorer import libcaer_packet
    libcaer_packet(events, 10**18)          # what the recorder writes into the bag
after_decode = loaded()
print(json.dumps({"n": int(events.size), "twin": after_twin, "encode": after_encode,
                  "warm": after_warm, "decode": after_decode}))
"""


@pytest.mark.parametrize("model", ["evk4", "dvxplorer", "davis346"])
def test_the_first_chunk_loads_no_kernel(model):
    r = subprocess.run([sys.executable, "-c", CHECK, model], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["n"] == 500
    assert sum(got["twin"].values()) > 0, "the twin loaded no encoder kernel when made"
    assert got["encode"] == got["twin"], "the twin's first chunk loaded a kernel the twin had not"
    assert got["decode"] == got["warm"], "the driver's first chunk loaded a kernel warm_up() had not"
