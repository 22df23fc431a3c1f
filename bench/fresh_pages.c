/* What a page the process has never touched costs on this machine (BENCHMARKS.md, point-cloud
 * fusion): the fusion bench's new rows land in such pages, and on the project's VMs their first
 * write costs far more than the memory traffic.
 *
 *   gcc -O2 -o /tmp/fresh_pages bench/fresh_pages.c && /tmp/fresh_pages
 *
 * Prints the time of a first write (memset) into 30 MB of fresh anonymous memory (the size of the
 * 512-d bench frame's 14.4k new rows): three times in a row, each reusing the pages the one before
 * just gave back; then right after first-touching 3 GB (as a bench run does when it copies its
 * map), and once more after that. A second write into the same pages is the bandwidth baseline. */
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>

static double now_ms(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec * 1e3 + t.tv_nsec / 1e6;
}

/* First and second write into `bytes` of fresh memory, in ms; the pages are given back after. */
static void fresh_write(const char *what, size_t bytes) {
    char *p = mmap(NULL, bytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (p == MAP_FAILED) {
        perror("mmap");
        return;
    }
    double t = now_ms();
    memset(p, 1, bytes);
    double first = now_ms() - t;
    t = now_ms();
    memset(p, 2, bytes);
    double second = now_ms() - t;
    printf("%-40s first write %7.1f ms (%5.2f us a 4 KiB page), second %5.1f ms\n", what, first,
           first * 1e3 / (bytes / 4096.0), second);
    munmap(p, bytes);
}

int main(void) {
    const size_t rows = 30ul << 20, big = 3ul << 30;
    for (int i = 0; i < 3; i++) fresh_write("30 MB", rows);
    char *q = mmap(NULL, big, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (q == MAP_FAILED) {
        perror("mmap");
        return 1;
    }
    double t = now_ms();
    memset(q, 1, big);
    double touch = now_ms() - t;
    printf("%-40s first write %7.1f ms (%5.2f us a 4 KiB page)\n", "3 GB", touch,
           touch * 1e3 / (big / 4096.0));
    fresh_write("30 MB right after the 3 GB", rows);
    fresh_write("30 MB once more", rows);
    munmap(q, big);
    return 0;
}
