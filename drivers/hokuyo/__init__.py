"""Hokuyo UTM-30LX-EW (SCIP 2.0): sans-IO codec (``scip``), clock mapping (``clock``), async client
(``client.HokuyoClient``), emulator (``emulator.HokuyoEmulator``), ``glassmap hokuyo`` commands (``cli``)
and the decode benchmark (``bench``)."""
