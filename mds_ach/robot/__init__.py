"""The robot's description and the channel contracts: joint table (YAML, anatomy XML), robot variants,
motion bounds, the wire structs (``msgs/``) and the contracts registry (``contracts``: every channel's name,
struct, writers, readers and validator, declared once), typed channels and who may write them (``access``).

May import: ``mds_ach.ach``, ``mds_ach.bus``.
"""
