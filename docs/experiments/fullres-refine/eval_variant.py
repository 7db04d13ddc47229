"""python3 docs/experiments/fullres-refine/eval_variant.py '{"MIN_BAND":8,"MAX_BAND":8}' -- <muir.evaluate args>: the evaluation with
the refinement twin's constants changed (module attributes of muir.fullres, read at call time)."""
import json, sys
sys.path.insert(0, __import__('os').path.join(__import__('os').path.dirname(__import__('os').path.abspath(__file__)), '../../../python'))
from muir import fullres as F
from muir import evaluate as E
for k, v in json.loads(sys.argv[1]).items():
    assert hasattr(F, k), k
    setattr(F, k, v)
sys.argv = [sys.argv[0]] + sys.argv[3:]
sys.exit(E.main())
