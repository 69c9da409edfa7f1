"""The report of a grid of online runs (the paper's learner): by episodes, with the paper's
claims (:mod:`.report`, :mod:`.summary`, :mod:`.tables`, :mod:`.claims`)."""
