"""The paper's experiments: grid specs (:mod:`.grid`), running them on a local process pool
or a Ray cluster (:mod:`.reproduce`), the report (:mod:`.report`) and the analytic figures
(:mod:`.figures`)."""
