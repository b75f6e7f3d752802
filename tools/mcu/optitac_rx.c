/*
 * optitac_rx.c - MCU-side receiver for tests: print the CONTACT frames of a byte stream.
 *
 *   optitac_rx [-n N] [-t IDLE_S] [-q] [PATH]
 *
 * Reads PATH (a file, a tty/pty device; "-" or nothing: stdin, e.g. a pty master fd
 * passed as stdin) and prints, line-buffered, a CSV header then one line per CONTACT
 * frame in wire units:
 *   seq,t_us,flags,x,y,major,minor,angle,strength,shape,confidence,age
 * (-q: no header). Stops at end of input (EOF, or EIO when a pty's other side closes),
 * after N CONTACT frames (-n), or after IDLE_S seconds without a byte (-t). Then prints
 * on stderr one summary line:
 *   frames=F contact=C status=S ack=A other=O bad_payload=P cobs=.. length=.. crc=.. version=.. overflow=..
 * Exit status: 0 end of input or N reached, 3 idle timeout, 2 usage/open error.
 * A tty is switched to raw mode (no echo, no CR/LF translation).
 */
#define _POSIX_C_SOURCE 200809L
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <termios.h>
#include <unistd.h>

#include "optitac_proto.h"

static void make_raw(int fd)
{
    struct termios t;
    if (!isatty(fd) || tcgetattr(fd, &t) != 0)
        return;
    t.c_iflag &= (tcflag_t) ~(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON | IXOFF);
    t.c_oflag &= (tcflag_t)~OPOST;
    t.c_lflag &= (tcflag_t) ~(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
    t.c_cflag &= (tcflag_t) ~(CSIZE | PARENB);
    t.c_cflag |= CS8 | CREAD | CLOCAL;
    t.c_cc[VMIN] = 1;
    t.c_cc[VTIME] = 0;
    (void)tcsetattr(fd, TCSANOW, &t);
}

int main(int argc, char **argv)
{
    long max_frames = -1;
    double idle_s = -1.0;
    int header = 1, fd = STDIN_FILENO, i, status = 0, done = 0;
    const char *path = NULL;
    unsigned long n_contact = 0, n_status = 0, n_ack = 0, n_other = 0, n_bad = 0;
    optitac_decoder_t d;
    optitac_frame_t f;
    uint8_t buf[512];

    for (i = 1; i < argc; i++) {
        if (strcmp(argv[i], "-n") == 0 && i + 1 < argc)
            max_frames = strtol(argv[++i], NULL, 10);
        else if (strcmp(argv[i], "-t") == 0 && i + 1 < argc)
            idle_s = strtod(argv[++i], NULL);
        else if (strcmp(argv[i], "-q") == 0)
            header = 0;
        else if (argv[i][0] == '-' && argv[i][1] != '\0') {
            fprintf(stderr, "usage: %s [-n N] [-t IDLE_S] [-q] [PATH]\n", argv[0]);
            return 2;
        } else
            path = argv[i];
    }
    if (path != NULL && strcmp(path, "-") != 0) {
        fd = open(path, O_RDONLY | O_NOCTTY);
        if (fd < 0) {
            perror(path);
            return 2;
        }
    }
    make_raw(fd);
    setvbuf(stdout, NULL, _IOLBF, 0);
    if (header)
        printf("seq,t_us,flags,x,y,major,minor,angle,strength,shape,confidence,age\n");
    optitac_decoder_init(&d);
    if (max_frames == 0)
        done = 1;
    while (!done) {
        ssize_t n;
        ssize_t k;
        if (idle_s >= 0.0) {
            fd_set rd;
            struct timeval tv;
            int r;
            FD_ZERO(&rd);
            FD_SET(fd, &rd);
            tv.tv_sec = (long)idle_s;
            tv.tv_usec = (long)((idle_s - (double)tv.tv_sec) * 1e6);
            r = select(fd + 1, &rd, NULL, NULL, &tv);
            if (r < 0 && errno == EINTR)
                continue;
            if (r == 0) {
                status = 3;
                break;
            }
        }
        n = read(fd, buf, sizeof buf);
        if (n < 0 && errno == EINTR)
            continue;
        if (n <= 0) /* EOF, or EIO: the other side of a pty closed */
            break;
        for (k = 0; k < n && !done; k++) {
            if (optitac_decoder_feed(&d, buf[k], &f) != OPTITAC_FEED_FRAME)
                continue;
            if (f.type == OPTITAC_T_CONTACT) {
                optitac_contact_t c;
                if (optitac_decode_contact(&f, &c) != 0) {
                    n_bad++;
                    continue;
                }
                printf("%u,%lu,%u,%d,%d,%u,%u,%d,%u,%u,%u,%u\n", (unsigned)f.seq, (unsigned long)f.t_us,
                       (unsigned)c.flags, (int)c.x, (int)c.y, (unsigned)c.major, (unsigned)c.minor,
                       (int)c.angle, (unsigned)c.strength, (unsigned)c.shape, (unsigned)c.confidence,
                       (unsigned)c.age_us);
                n_contact++;
                if (max_frames > 0 && (long)n_contact >= max_frames)
                    done = 1;
            } else if (f.type == OPTITAC_T_STATUS) {
                optitac_status_t s;
                if (optitac_decode_status(&f, &s) == 0)
                    n_status++;
                else
                    n_bad++;
            } else if (f.type == OPTITAC_T_ACK) {
                optitac_ack_t a;
                if (optitac_decode_ack(&f, &a) == 0)
                    n_ack++;
                else
                    n_bad++;
            } else {
                n_other++;
            }
        }
    }
    fprintf(stderr,
            "frames=%lu contact=%lu status=%lu ack=%lu other=%lu bad_payload=%lu cobs=%lu length=%lu "
            "crc=%lu version=%lu overflow=%lu\n",
            (unsigned long)d.counters.frames, n_contact, n_status, n_ack, n_other, n_bad,
            (unsigned long)d.counters.cobs, (unsigned long)d.counters.length, (unsigned long)d.counters.crc,
            (unsigned long)d.counters.version, (unsigned long)d.counters.overflow);
    if (fd != STDIN_FILENO)
        close(fd);
    return status;
}
