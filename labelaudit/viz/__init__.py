"""Pictures and the review report: ``labelaudit show`` (:mod:`.show`) and ``labelaudit report`` (:mod:`.report`).

Everything drawn is recomputed by the library functions of ``infer`` (:mod:`.objects`), with the
run's own configuration from the results manifest, so a picture always matches its results row.
Nothing here changes results; pictures use matplotlib's Agg backend and HTML a jinja2 template.
"""
