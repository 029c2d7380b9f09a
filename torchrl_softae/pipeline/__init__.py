"""The experiment pipeline on top of the library: ``softae`` CLI, typed configs, the method table,
exploration and evaluation runs, run directories, the env catalog and plots.

The rule: the pipeline imports the library, never the other way round.
"""
