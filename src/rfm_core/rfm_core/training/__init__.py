"""Training and fitting of rfm's learned parts on simulated scenes (seeds 3000+): the learned
object matcher (:mod:`.matcher`, ``rfm train-matcher``) and depth_clusters' calibrated score
(:mod:`.depth_score`, ``rfm train-depth-score``). The runtime packages (detection, matching,
mapping) never import this package, nor the simulator or the evaluation."""
