"""The science, with no I/O: box geometry (:mod:`.geometry`), the paper's posterior (:mod:`.posterior`),
the label-error fit (:mod:`.fit`), the spatial distribution and JIoU (:mod:`.spatial`), overlaps (:mod:`.iou`).

Nothing in ``core/`` reads or writes files, prints, or knows a dataset format; inputs are NumPy
arrays and the parameter dataclasses of :mod:`.params` (which :mod:`labelaudit.config` loads from TOML).
"""
