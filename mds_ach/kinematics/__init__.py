"""Kinematic model (numpy FK/Jacobian), inverse kinematics, the collision model.

May import: ``mds_ach.robot``.
"""
