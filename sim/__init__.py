"""Virtual machine tool, positioning units, interferometer and CNC behind xmalign's roles."""
