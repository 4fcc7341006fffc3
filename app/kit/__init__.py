"""The service's kit: small standard-library tools the service layers share, not numeric code.

Beside :mod:`app.clock`, :mod:`app.config` and :mod:`app.log`: outgoing requests and the one
rule for where they may go (:mod:`app.kit.net`), signed values and the service's signing key
(:mod:`app.kit.signing`), private files written once (:mod:`app.kit.files`), glibc allocator
tuning (:mod:`app.kit.allocator`) and the data directory's layout
(:mod:`app.kit.data_layout`).  The kit imports the core and the standard library, never the
database, jobs, services, web or viewer layers; ``app.core`` never imports the kit.
"""
