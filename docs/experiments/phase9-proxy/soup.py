"""Average the float weights of models of one config (a "model soup").

python3 docs/experiments/phase9-proxy/soup.py OUT.safetensors A.safetensors B.safetensors ...
"""
import os, sys, torch
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../../python"))
from muir.checkpoint import load_model, save_model
out = sys.argv[1]; srcs = sys.argv[2:]
ms = [load_model(p) for p in srcs]
sd = ms[0].state_dict()
avg = {}
for k, v in sd.items():
    if v.is_floating_point():
        avg[k] = sum(m.state_dict()[k] for m in ms) / len(ms)
    else:
        avg[k] = v
ms[0].load_state_dict(avg)
save_model(ms[0], out, {"soup_of": srcs})
print("wrote", out)
