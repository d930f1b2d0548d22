"""The run records: the typed record and its JSON, the limits it is judged by, the database (its
tables, its one migration path, its queries) and the spool of records the database could not take.

Below the pages and statistics (``report``, ``lot``, ``msa``), which read them, and the station's
cycle, which writes them."""
