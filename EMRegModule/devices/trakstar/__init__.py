"""The NDI/Ascension trakSTAR: :mod:`.protocol` (its RS-232 bytes and words, with their sources), :mod:`.driver`
(the pyserial client) and :mod:`.source` (the live sample source behind ``trakstar://`` URLs)."""
