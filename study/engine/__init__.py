"""Running a trained model: devices, distributed training, checkpoints, the code identity caches are
keyed on, training a run (`train`) and its gates (`gate_training`), the reference models, the prediction
pass (`predictions`) and the one scoring path (`scoring`)."""
