"""drivers: the robot's devices behind small interfaces, each with a real adapter and a fake.

May import ``lino_loc``; never ``services`` (checked by import-linter).
"""
