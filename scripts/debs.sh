#!/bin/sh
# debs.sh WHAT CONSEQUENCE PACKAGE...: make sure Debian packages are installed (as root or
# with password-less sudo); otherwise print one line saying what to run and what is lost
# meanwhile. Exit 0 when the packages are there, 1 when not (make carries on either way).
what=$1; consequence=$2; shift 2
missing=$(for p in "$@"; do dpkg-query -W -f='${Status}\n' "$p" 2>/dev/null \
  | grep -q 'ok installed' || echo "$p"; done | tr '\n' ' ')
[ -z "$missing" ] && exit 0
if [ "$(id -u)" = 0 ]; then sudo=; elif sudo -n true 2>/dev/null; then sudo="sudo -n"; else sudo=no; fi
if [ "$sudo" = no ] || ! command -v apt-get >/dev/null; then
  echo "$what: not installed (missing: ${missing% }); to install: sudo apt-get install $* (until then $consequence)"
  exit 1
fi
if ! { $sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo apt-get install \
    -y -qq --no-install-recommends "$@" >/dev/null; }; then
  echo "$what: apt-get install $* failed (until fixed $consequence)"
  exit 1
fi
