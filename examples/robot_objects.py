"""Print each object's world_T_object as the recognition worker publishes it (uses only schemas)."""

import sys

from schemas import codec, keys, messages
from schemas.bus import Bus, TransportConfig

endpoint, cell = (sys.argv[1:3] + ["tcp/127.0.0.1:7447", "demo"][len(sys.argv[1:3]) :])[:2]
with Bus(TransportConfig(connect=[endpoint]), cell) as bus:
    sub = bus.subscribe(keys.objects(cell), messages.ObjectDetections)
    while True:
        item = sub.get(timeout_s=1.0)
        for obj in item.msg.objects if item else []:
            T = codec.pose_from_msg(obj.world_T_object)  # world_T_object, metres
            print(obj.object_id, *T[:3, 3].round(3), "seen by", ",".join(obj.camera_ids), flush=True)
