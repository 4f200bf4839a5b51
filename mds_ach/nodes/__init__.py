"""The processes of the pipeline: daemon, mux, filter, collision gate, IK node, and their shared plumbing.

Each node module has a module-level rclpy ``Node`` subclass, a ``PARAMETERS`` tuple (declared with descriptions
and ranges, read at start; docs/parameters.md's table and config/params.yaml are rendered from them) and a
``main`` built on ``rosnode.run_node``, which the bridge (``mds_ach_bridge``) uses too. ``pipeline`` holds the
rclpy-free helpers (reference arrays, joint selections, start-up reference, re-seeding, channel guard, schedule).

May import: ``ach``, ``bus``, ``robot``, ``kinematics``.
"""
