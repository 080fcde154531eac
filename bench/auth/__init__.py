"""What authenticated datagrams and the proofs of freshness cost: bytes, CPU and join time.

Four measures, each signed and unsigned (open and keyed) side by side in the same run:

1. bytes: every kind of datagram a robot sends (search, ping, compact reply, beacon, a
   one-service delta, a full Update part, Byebye), encoded as the daemon encodes them, then
   sealed with a counter of the size a robot reaches in a day (6 digits), for the fleet or for
   one robot as the daemon seals it;
2. CPU: microseconds per datagram to seal and to check a seal (sdfr.protocol.auth), and for the
   whole
   receive path of the protocol core (seal check, decode, freshness, bookkeeping) fed a
   stream of beacons and pings of a peer it has proven (in a two-robot simulator run);
   medians of repeated timed loops;
3. a fleet: 6 robots with 100 services each, 5 minutes of virtual time at the product's 10 s
   beacon (the protocol core on an in-memory medium, sdfr.testing.simnet), bytes each robot
   sent and received (UDP payload), open and keyed;
4. dynamics: the same fleet (6 robots, 100 services, CoreConfig defaults), open and keyed,
   over several seeds and at two link delays (1-4 ms and 20-50 ms one way): how long a new
   robot takes to join (from its start until every other robot lists it with its whole set and
   it lists every other robot with theirs), a robot restarted (gracefully, and killed and back
   5 s later) until it is listed again everywhere at its new boot; and the bytes on the air per
   robot per minute in an idle fleet and in a churning one (a service change every 10 s on
   one robot after the other), with how long each change takes to be listed everywhere.

`--baseline REV|DIR` runs the same bench code against another sdfr package (a git revision,
extracted with `git archive`, or a checkout such as a `git worktree`) in a child process, and
adds its figures and a side-by-side table (baseline vs this checkout) to the JSON.

JSON on stdout and in --out (runs/bench-auth.json); a table on stderr.

Files: `fixtures` (the key, the seal, services, the two fleets), `datagrams` (measures 1 and
2), `fleet` (3), `dynamics` (4), `baseline` (which sdfr was measured; another beside it),
`report` (the table), `__main__` (the command).
"""
