"""Pioneer 3-DX (ARCOS/P2OS): sans-IO codec (``packets``, ``sip``), odometry (``odometry``), async client
(``client.PioneerClient``), emulator (``emulator.PioneerEmulator``), CLI (``cli``). See README.md here."""
