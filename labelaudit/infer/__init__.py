"""``labelaudit infer``: the Open3D crop (:mod:`.crop`), frame → rows (:mod:`.rows`) and the run (:mod:`.run`).

The run plans chunks, resumes and hands them to an executor (:mod:`labelaudit.executors`); rows are
built in one place (:mod:`.rows`) from the column definitions of :mod:`labelaudit.results`.
"""
