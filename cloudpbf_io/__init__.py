"""cloudpbf's file utilities, shared by both solvers and the harness and below all of them.

* :mod:`cloudpbf_io.files`: the one atomic writer (temporary name, fsync, ``os.replace``, fsync of
  the folder) and the clean-up of temporary files an interrupted writer left;
* :mod:`cloudpbf_io.export`: ParaView (VTK), Houdini (.bgeo) and xarray layouts of particle states and
  gridded fields, with their units;
* :mod:`cloudpbf_io.bgeo`: Houdini's classic binary .bgeo (numpy writer and reader);
* :mod:`cloudpbf_io.progress`: progress reports for a terminal and for a log.

Needs numpy alone at import time; imports nothing of ``pbf_cuda``, ``grid_baseline`` or ``cloudpbf``.
"""
