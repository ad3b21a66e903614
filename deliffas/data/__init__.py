"""DynaCap/Skeletool readers and writers, synthetic captures, HDF5 shards and the streaming dataset."""
