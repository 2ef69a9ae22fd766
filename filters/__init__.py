"""slam-gym's estimation library: numpy/scipy (and threadpoolctl for the BLAS thread limit of
:mod:`filters.blas`) only, importing nothing else of the project."""
