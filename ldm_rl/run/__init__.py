"""Run plumbing shared by every recipe, apart from the method: checkpoints (:mod:`.checkpoint`), stopping on a
signal (:mod:`.signals`), a run folder's files and loggers (:mod:`.outputs`), progress lines (:mod:`.progress`),
the recipes' ``--help`` (:mod:`.help`) and command-line pre-flight (:mod:`.cli`)."""
