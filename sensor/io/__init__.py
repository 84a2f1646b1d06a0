"""Files: spike files of every layout, frames folders (EXR irradiance), atomic writes, locks and
the fused array passes of the streaming readers and writers.
"""
