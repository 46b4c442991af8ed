"""Files the package writes: atomic writes and JSON (``files``), figures without pyplot (``drawing``) and the
record of where a result came from (``provenance``). Imports nothing else of jaxtraffic."""
