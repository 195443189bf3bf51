"""One run over several hosts: the hosts file, a router per host, remote processes, docker compose, a namespace lab."""
