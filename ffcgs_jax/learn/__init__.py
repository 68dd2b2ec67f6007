"""`ffcgs learn`: a hand's learned sampler and ranker from its spec, in one resumable run (`pipeline.learn_hand`)."""
