"""The live gateway: settings of the live sections, the estimator fed by windows, the CNC link, the runtime."""
