"""Spraying a field: the coverage plan over a scene's rows (:mod:`.coverage`), flown with the spray on
(:mod:`.mission`), and the trials and figures of :mod:`droneulator.spray.trials` (:mod:`.report`)."""
