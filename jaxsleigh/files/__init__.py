"""Results on disk: the npz writer and readers, the chunk store and its fingerprints, run locks, processes sharing one run. Imports only the base modules and the model."""
