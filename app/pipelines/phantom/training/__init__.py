"""Training the phantom CNN: labelled pillars and their windows (`dataset`), training from
reference-labelled surveys with k-fold validation and the model card (`train`), fine-tuning on
pillars people labelled (`finetune`). The only phantom code that imports the simulator."""
