"""Where the computation runs: host devices (``devices``), cooperating processes (``distributed``), the
persistent compilation cache (``compile_cache``) and the traced-or-concrete test of inputs (``tracing``).
Imports nothing else of jaxtraffic."""
