"""The trojan-detection benchmark: a zoo split into train, test and holdout (:mod:`.splits`), what a detector sees
of a model (:mod:`.suspect`), the detector API and the registered detectors (:mod:`.detectors`), TrojAI's scores
with bootstrap intervals (:mod:`.scoring`) and the leaderboard that fits and scores every detector
(:mod:`.leaderboard`, ``seqtrojan zoo detect --zoo Z --out S``)."""
