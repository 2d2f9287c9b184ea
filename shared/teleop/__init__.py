"""Teleoperation maths every mapping shares: the master point, the master frame, the operator's scale.

:mod:`.master` (the mapped master point: pen or virtual trocar), :mod:`.work_frame` and
:mod:`.camera_frame` (the master frame's axes in the slave base frame), :mod:`.scale` (the
operator's scale commands). Used by the mapping service's engage state machine and by the robots'
mapping strategies (``shared/robots/<name>/mapping.py``).
"""
