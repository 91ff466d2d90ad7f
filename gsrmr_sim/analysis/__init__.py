"""After a run: console tools that read recorded ``gsrmr-demo`` reports (``reports/demo-*``) and print tables.

One module each, each with a ``main(argv=None) -> int`` behind a console script (README.md, "Reading recorded
runs"): ``gsrmr-regret-split`` (:mod:`.regret_split`), ``gsrmr-key-estimates`` (:mod:`.key_estimates`),
``gsrmr-planner-replay`` (:mod:`.planner_replay`), ``gsrmr-planner-tail`` (:mod:`.planner_tail`) and
``gsrmr-plausibility-replay`` (:mod:`.plausibility_replay`). Hindsight where they say so: nothing here runs live.
"""
