"""Update one vhm_viz filter on every rank and print each rank's error and output size.

Usage: ``mpiexec -n N pvbatch --symmetric rank_errors.py CONFIG.json`` with CONFIG holding
``input`` (a volume), optional ``voi`` (a sub-extent of it: fewer planes than ranks leave
a rank with an empty piece), ``filter``, ``scene`` and ``cage``, and optional
``cage_on_rank_0_only`` (an update that succeeds first, then one whose cage reaches rank 0
only). Every rank runs this script
(``--symmetric``) and prints ``vhm-rank R: points N error TEXT vhm-end``: its filter's
output size and ``last_error``, and ``vhm-state R: warnings N folds BOOL vhm-end``: how many
warnings describe its output, and whether a fold summary does.
"""

import json
import sys

import paraview.simple as pvs
from vtkmodules.vtkParallelCore import vtkMultiProcessController as C

cfg = json.load(open(sys.argv[1]))
c = C.GetGlobalController()
rank = 0 if c is None else c.GetLocalProcessId()
src = pvs.OpenDataFile(cfg["input"])
if cfg.get("voi"):
    src = pvs.ExtractSubset(Input=src, VOI=cfg["voi"])
cage = pvs.OpenDataFile(cfg["cage"])
flt = getattr(pvs, cfg["filter"])(Input=src, Cage=cage, SceneFile=cfg["scene"])
if cfg.get("cage_on_rank_0_only"):  # first an update that succeeds, then a cage on rank 0
    pvs.UpdatePipeline(proxy=flt)
    only = pvs.ProgrammableFilter(Input=cage)
    only.OutputDataSetType = "vtkPolyData"
    only.Script = (
        "from vtkmodules.vtkParallelCore import vtkMultiProcessController as C\n"
        "c = C.GetGlobalController()\n"
        "if c is None or c.GetLocalProcessId() == 0:\n"
        "    self.GetOutput().ShallowCopy(self.GetInput())\n"
        "else:\n"
        "    self.GetOutput().Initialize()\n"
    )
    flt.Cage = only
pvs.UpdatePipeline(proxy=flt)
obj = flt.GetClientSideObject()
out = obj.GetOutputDataObject(0)
folds = getattr(obj, "fold_cells", None)
said = len(obj.warnings)
print(f"vhm-state {rank}: warnings {said} folds {folds is not None} vhm-end", flush=True)
# (the ranks share one stdout: a line may start after another rank's unfinished one)
print(
    f"vhm-rank {rank}: points {out.GetNumberOfPoints()} error {obj.last_error} vhm-end", flush=True
)
