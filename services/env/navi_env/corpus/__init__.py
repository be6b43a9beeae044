"""Training corpora: the scenes a run trains and evaluates on.

folder.py    a corpus folder (.gmdag files and manifest.json): build it transactionally, load it
jobs.py      the procedural default corpus built over compile jobs on the compiler workers
"""
