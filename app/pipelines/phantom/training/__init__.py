"""Training the phantom CNN: labelled pillars and their windows (`dataset`), k-fold training and
the model card (`train`), the training set from simulated and reference-labelled surveys and the
whole training command (`from_surveys`, the only phantom code that imports the simulator),
fine-tuning on pillars people labelled (`finetune`)."""
