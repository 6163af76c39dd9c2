"""Caillette, Galata and Howard's tracker (CVIU 2007, the second seed): a learnt behaviour
model (Gaussian clusters of joint angles and their derivatives, :mod:`.clusters`, and a
variable length Markov model over the cluster labels, :mod:`.vlmm`) and the evaluation by
Gaussian blobs and the closed-form relative entropy (:mod:`.kl`). Pure cores, no bus."""
