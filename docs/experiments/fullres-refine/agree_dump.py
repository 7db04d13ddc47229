import os, subprocess, numpy as np, sys
from PIL import Image
sys.path.insert(0, '/work/main/python')
from muir import data as D
MUIR = '/work/main/target/release/muir'
crops = [("middlebury2001/tsukuba", 32, 24), ("middlebury2003/teddy", 100, 80), ("middlebury2005/Art", 120, 100), ("middlebury2006/Aloe", 90, 90), ("eth3d_twoview/playground", 400, 150)]
W, H = 320, 240
for name, x, y in crops:
    d = os.path.join('/work/shared/data', name)
    key = name.replace('/', '__')
    os.makedirs(key, exist_ok=True)
    for v in ('left', 'right'):
        Image.open(os.path.join(d, f'{v}.png')).convert('RGB').crop((x, y, x + W, y + H)).save(f'{key}/{v}.png')
    for eng, model in (('fixed', 'models/muir-slim.muirq'), ('wide', 'models/muir-slim-wide.muirq'), ('float', 'models/muir-slim.safetensors')):
        r = subprocess.run([MUIR, 'run', '--model', '/work/main/' + model, '--left', f'{key}/left.png', '--right', f'{key}/right.png', '--no-refine',
                            '--disparity', f'{key}/{eng}_d.pfm', '--uncertainty', f'{key}/{eng}_u.pfm'], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    print(key, flush=True)
