"""What operators run: the ``mds-ach`` CLI, console, read monitor, viewer, channel tools, the C header
generator, the CAN-log auditor.

May import everything below it.
"""
