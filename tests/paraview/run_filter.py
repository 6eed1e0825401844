"""Run one vhm_viz ParaView filter with pvpython/pvbatch and write its output in parallel.

Usage: ``[mpiexec -n N] pvbatch run_filter.py CONFIG.json`` where CONFIG holds
``input`` (a file ParaView reads), ``filter`` ("VHMHarmonicDeformation", ...), ``scene``,
optional ``cage`` (a file connected to the Cage port; ``update_cage_first`` updates its
reader before the filter exists), ``redistribute`` (spread a
surface or mesh over the ranks first), ``properties`` (extra proxy properties) and
``output`` (a parallel VTK XML file: .pvtp, .pvtu, .pvts, .pvti). A point array
``vhm_id`` (the input point index) is added first, so that results can be matched point by
point whatever the ranks did with the order.
"""

import json
import sys

import paraview.simple as pvs
from paraview import servermanager
from paraview.simple import (
    GenerateIds,
    OpenDataFile,
    ProgrammableFilter,
    RedistributeDataSet,
    SaveData,
    UpdatePipeline,
)

config = json.load(open(sys.argv[1]))
data = OpenDataFile(config["input"])
source = data
if config.get("ids", True):
    source = GenerateIds(Input=source)
    source.PointIdsArrayName = "vhm_id"
    source.CellIdsArrayName = "vhm_cell_id"
if config.get("redistribute"):
    source = RedistributeDataSet(Input=source)
kwargs = {"Input": source}
if config.get("cage"):
    cage = OpenDataFile(config["cage"])
    if config.get("cage_on_rank_0_only"):  # what a rank-0-only reader delivers
        cage = ProgrammableFilter(Input=cage)
        cage.OutputDataSetType = "vtkPolyData"
        cage.Script = (
            "from vtkmodules.vtkParallelCore import vtkMultiProcessController as C\n"
            "c = C.GetGlobalController()\n"
            "if c is None or c.GetLocalProcessId() == 0:\n"
            "    self.GetOutput().ShallowCopy(self.GetInput())\n"
            "else:\n"
            "    self.GetOutput().Initialize()\n"
        )
    if config.get("update_cage_first"):  # as a script that shows the cage first does
        UpdatePipeline(proxy=cage)
    kwargs["Cage"] = cage
flt = getattr(pvs, config["filter"])(**kwargs)
if config.get("scene") is not None:
    flt.SceneFile = config["scene"]
for name, value in config.get("properties", {}).items():
    setattr(flt, name, value)
UpdatePipeline(proxy=flt)
print(f"vhm-paraview-points: {flt.GetDataInformation().GetNumberOfPoints()}")
n = servermanager.ActiveConnection.GetNumberOfDataPartitions()
if config.get("output") is not None:  # (no sys.exit: under MPI every rank must finish)
    # ParaView offers the parallel XML writers (.pvtp, .pvtu, ...: one piece per rank) only
    # when it runs on several ranks; serially the plain format is the same data in one piece
    stem, ext = config["output"].rsplit(".", 1)
    output = f"{stem}.{ext[1:]}" if n == 1 and ext.startswith("pvt") else config["output"]
    SaveData(output, proxy=flt)
    print(f"vhm-paraview-run: {config['filter']} on {n} rank(s) -> {output}")
