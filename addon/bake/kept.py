"""Results kept from one bake to the next (an animation's frames): small dicts, most recently
kept last, holding at most a given number of entries.  Each user keys its results by what they
are a function of (a hash of their inputs, or inputs it checks itself), so a kept result is
exactly the one a fresh computation would give."""


def keep_recent(cache, key, value, size):
    """Keep ``value`` under ``key`` in ``cache`` as its most recent entry, dropping the oldest
    beyond ``size`` entries; returns ``value``."""
    cache.pop(key, None)
    cache[key] = value
    while len(cache) > size:
        cache.pop(next(iter(cache)))
    return value
