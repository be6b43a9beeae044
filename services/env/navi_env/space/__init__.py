"""A scene's free space and what the sim draws from it: spawns and point goals.

freespace.py    a scene's free space at the drone's radius as voxels, its connected parts, geodesic fields
qualify.py      spawn qualification: probe candidate positions, keep those with a useful view
goal_tables.py  point-goal tables: goals the spawns reach within a range of true path length, their fields
"""
