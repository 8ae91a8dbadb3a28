"""A/B of mapping.registration_sigma on one demo recording: replay it (the scans the live run processed) with
each setting and score the glass map with the demo's rule. Usage, from the repository:
PYTHONPATH=. python docs/results/loop-closure/sigma/demo_ab.py out/demo/demo.mcap office"""
import os
import sys

import numpy as np

from glassmap.sim.world import load_world
from runtime.evaluate import evaluate_map
from runtime.replay import recorded_config, replay_file, with_settings

path, world = sys.argv[1], sys.argv[2]
seen = np.load(os.path.join(os.path.dirname(path), "seen_cells.npy"))
for s in ("anchor", "map"):
    res = replay_file(path, with_settings(recorded_config(path), registration_sigma=s), progress=False)
    ev = evaluate_map(res._processor.mapper, load_world(world), seen=seen)
    print(f"sigma {s}: scans {res.scans}, error {100 * ev.error:.2f} %, glass recall {100 * ev.glass_recall:.2f} %, "
          f"false glass {100 * ev.false_glass_rate:.2f} %, unregistered {100 * ev.unregistered:.2f} %")
