"""slam-gym's estimation library: numpy/scipy only, importing nothing else of the project."""
