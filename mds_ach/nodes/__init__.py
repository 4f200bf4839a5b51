"""The processes of the pipeline: daemon, mux, filter, collision gate, IK node, and their shared plumbing.

May import: ``ach``, ``bus``, ``robot``, ``kinematics``.
"""
