"""The report of a grid of batch runs (``kind = "batch"``): by environment steps and over tasks
(:mod:`.report`, :mod:`.results`, :mod:`.summary`, :mod:`.tables`, :mod:`.aggregate`,
:mod:`.figures`)."""
