"""Reproducing the paper: its published figures (`paper`), the evidence measured on the shipped
policies (`evidence`, `cfrace reproduce`) and its report (`report`), and the training pipeline that
makes those policies (`pipeline`, policies/pipeline.yaml) with each stage's checkpoint choice (`select`)."""
