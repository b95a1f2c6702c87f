"""Schedules' triggers: a 5-field crontab read as cron reads it.

APScheduler's ``CronTrigger.from_crontab`` numbers the days of the week from Monday (0),
where cron numbers them from Sunday (0 or 7): handed over as it is, ``0 3 * * 1`` fires on
Tuesdays and ``1-5`` runs Tuesday to Saturday. Day-of-week fields are translated to day
names here. Cron runs a job when either restricted day field matches, APScheduler only
when both do, so a crontab restricting both is refused rather than run differently.
"""

from __future__ import annotations

CRON_DAYS = ("sun", "mon", "tue", "wed", "thu", "fri", "sat")


def cron_weekdays(field: str) -> str:
    """A crontab day-of-week field (0 or 7 = Sunday, 1 = Monday, names, ranges, steps) as
    APScheduler day names."""
    if field == "*":
        return "*"

    def day(token: str) -> int:
        token = token.lower()
        if token in CRON_DAYS:
            return CRON_DAYS.index(token)
        if token.isdigit() and 0 <= int(token) <= 7:
            return int(token) % 7
        raise ValueError(f"day of week {token!r} is not 0-7 or sun-sat")

    days: set[int] = set()
    for part in field.split(","):
        span, _, step_text = part.partition("/")
        step = int(step_text) if step_text.isdigit() and int(step_text) > 0 else None
        if step_text and step is None:
            raise ValueError(f"day of week {part!r}: bad step")
        if span == "*":
            lo, hi = 0, 6
        elif "-" in span:
            lo_text, hi_text = span.split("-", 1)
            lo, hi = day(lo_text), day(hi_text)
            hi = 7 if hi_text == "7" or (hi == 0 and lo > 0) else hi
            if hi < lo:
                raise ValueError(f"day of week {part!r}: range runs backwards")
        else:
            lo = hi = day(span)
            if step is not None:
                hi = 6
        days.update(d % 7 for d in range(lo, hi + 1, step or 1))
    return ",".join(CRON_DAYS[d] for d in sorted(days))


def cron_trigger(text: str):
    """The APScheduler trigger (UTC) of a 5-field crontab, read as cron reads it;
    ``ValueError`` naming what cannot be read."""
    from apscheduler.triggers.cron import CronTrigger

    fields = text.split()
    if len(fields) != 5:
        raise ValueError(f"{len(fields)} fields, expected 5 (minute hour day month weekday)")
    minute, hour, day, month, weekday = fields
    if day != "*" and weekday != "*":
        raise ValueError("it restricts both day of month and day of week (cron runs on "
                         "either, the scheduler would need both); give one of them")
    return CronTrigger(minute=minute, hour=hour, day=day, month=month,
                       day_of_week=cron_weekdays(weekday), timezone="UTC")
