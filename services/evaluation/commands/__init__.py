"""The CLI modules of the research harness: ``lino-loc eval ...`` (:mod:`.eval_cmd`) and
``lino-loc bench ...`` (:mod:`.bench_cmd`), registered by :mod:`services.cli`."""
