"""The NDI Aurora: :mod:`.protocol` (NDI's serial API: CRC16, BX/TX/PHSR/PHINF formats, with their sources),
:mod:`.driver` (the client on ndicapi) and :mod:`.source` (the live sample source behind ``aurora://`` URLs)."""
