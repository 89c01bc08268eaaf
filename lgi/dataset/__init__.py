"""The shape dataset: storage, OBJ import, head stabilisation, marker layouts, mesh geometry."""
