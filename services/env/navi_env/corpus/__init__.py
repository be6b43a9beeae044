"""Training corpora: the scenes a run trains and evaluates on.

folder.py    a corpus folder (.gmdag files and manifest.json): build it transactionally, load it
qualify.py   spawn qualification: probe candidate positions, keep those with a useful view
jobs.py      the procedural default corpus built over compile jobs on the compiler workers
freespace.py a scene's free space at the drone's radius as voxels, its connected parts, geodesic fields
goals.py     point-goal tables: goals the spawns reach within a range of true path length, their fields
"""
